"""Command-line helpers shared by the scripts: argument types that reject bad values at parse
time, output checks made before any simulation runs, and vectors that start with a minus sign.

Every check ends in the parser's own error (``parser.error``: usage, message, exit status 2).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import re
from argparse import SUPPRESS
from collections.abc import Sequence
from pathlib import Path

# A comma-separated list of numbers ("-0.045,0.012,-0.03"): argparse takes a token that starts
# with "-" and is not a plain number for an option, so such a value after a space is rejoined to
# its option with "=" before parsing (see join_vector_values).
_NUMBER_LIST = re.compile(r"^[-+]?[\d.eE+-]*(,[-+]?[\d.eE+-]*)+$")


def positive_int(text: str) -> int:
    """An integer >= 1."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return value


def nonnegative_int(text: str) -> int:
    """An integer >= 0 (seeds: numpy's generators take no negative seed)."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer >= 0, got {value}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0."""
    value = _float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    value = _float(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be a number >= 0, got {text}")
    return value


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"must be finite, got {text}")
    return value


class VectorAction(argparse.Action):
    """An option taking n numbers, written either comma-separated as one value
    (``--cargo-com=-0.045,0.012,-0.03``; after a space too, see join_vector_values) or as n
    values (``--cargo-com -0.045 0.012 -0.03``). Stores a tuple of n floats."""

    def __init__(self, option_strings, dest, size: int, **kwargs) -> None:
        self.size = size
        kwargs.setdefault("metavar", "X")
        super().__init__(option_strings, dest, nargs="+", **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        parts = [p for v in values for p in v.split(",")]
        if len(parts) != self.size:
            parser.error(
                f"argument {option_string}: expected {self.size} numbers (comma-separated or "
                f"separated by spaces), got {len(parts)}: {' '.join(values)}"
            )
        try:
            setattr(namespace, self.dest, tuple(_float(p) for p in parts))
        except argparse.ArgumentTypeError as err:
            parser.error(f"argument {option_string}: {err}")


def join_vector_values(argv: Sequence[str], options: Sequence[str]) -> list[str]:
    """argv with ``OPTION VALUE`` written as ``OPTION=VALUE`` where OPTION is one of ``options``
    and VALUE a comma-separated list of numbers, so that a first number with a minus sign is not
    taken for an option (argparse reads "-0.045,0.012" as an unknown option)."""
    out: list[str] = []
    k = 0
    while k < len(argv):
        if argv[k] in options and k + 1 < len(argv) and _NUMBER_LIST.match(argv[k + 1]):
            out.append(f"{argv[k]}={argv[k + 1]}")
            k += 2
        else:
            out.append(argv[k])
            k += 1
    return out


def output_dir(parser: argparse.ArgumentParser, path: Path, option: str) -> Path:
    """``path`` created if missing and checked writable, else the parser's error."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parser.error(f"{option}: cannot create folder {path}: {err.strerror or err}")
    if not os.access(path, os.W_OK | os.X_OK):
        parser.error(f"{option}: folder {path} is not writable")
    return path


def output_file(
    parser: argparse.ArgumentParser, path: Path, option: str, suffix: str | None = None
) -> Path:
    """``path``'s folder created if missing and checked writable, ``path`` not a folder and
    ending in ``suffix`` if given, else the parser's error."""
    if suffix is not None and path.suffix.lower() != suffix:
        parser.error(f"{option} must end in {suffix}, got {path}")
    if path.is_dir():
        parser.error(f"{option}: {path} is a folder, not a file")
    output_dir(parser, path.parent, f"{option}'s folder")
    return path


def json_object_file(parser: argparse.ArgumentParser, path: Path, option: str) -> dict:
    """The JSON object already in ``path`` (empty dict if the file does not exist), else the
    parser's error: results are merged into it, so it must hold one JSON object."""
    output_file(parser, path, option)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        reason = "is empty" if path.stat().st_size == 0 else f"is not JSON ({err})"
        parser.error(
            f"{option}: {path} {reason}; results are merged into a JSON object, so give a new "
            f"file or one this script wrote"
        )
    if not isinstance(data, dict):
        parser.error(f"{option}: {path} holds a JSON {type(data).__name__}, not an object")
    return data


def check(parser: argparse.ArgumentParser, ok: bool, message: str) -> None:
    """The parser's error with ``message`` unless ``ok``."""
    if not ok:
        parser.error(message)


class Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """--help lists every option with its default (options without a help text too) and keeps
    the description's line breaks."""

    def _format_action(self, action: argparse.Action) -> str:
        if action.help is None and action.option_strings and action.default is not SUPPRESS:
            action = copy.copy(action)
            action.help = "(default: %(default)s)"
        return super()._format_action(action)


def trajectory(text: str) -> str:
    """A trajectory name: one of ``Trajectory.NAMES``, "excite", or the path of a readable
    design JSON file (``agents.excitation``); the team size is checked after parsing
    (``check_trajectory``)."""
    from astrocargo.agents.excitation import is_trajectory_name, load_design, trajectory_choices

    if not is_trajectory_name(text):
        raise argparse.ArgumentTypeError(f"unknown trajectory {text!r}; {trajectory_choices()}")
    if text.endswith(".json"):
        try:
            load_design(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
    return text


def check_trajectory(
    parser: argparse.ArgumentParser, name: str, n_robots: int, fast: bool = False
) -> None:
    """The parser's error unless trajectory ``name`` can be flown by ``n_robots`` robots (a
    design file made for another team size, ``fast`` with a design)."""
    from astrocargo.agents.excitation import check_trajectory as check

    try:
        check(name, n_robots, fast)
    except ValueError as err:
        parser.error(f"--trajectory: {err}")


def limits_parser(doc: str, min_robots: int) -> argparse.ArgumentParser:
    """The parser of the estimation-limits scripts: one flight's scenario (robots, trajectory,
    duration) flown for each of ``--seeds`` by ``--workers`` processes; ``doc`` the script's
    docstring (its first paragraph is the description)."""
    from astrocargo.envs.world import MAX_ROBOTS

    parser = argparse.ArgumentParser(
        description=doc.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--robots", type=positive_int, default=2, help=f"{min_robots} to {MAX_ROBOTS}"
    )
    parser.add_argument(
        "--trajectory", type=trajectory, default="figure8_tumble", help="a name or a design"
    )
    parser.add_argument("--duration", type=positive_float, default=90.0, help="s, >= 8")
    parser.add_argument("--seeds", type=nonnegative_int, nargs="+", default=[0], help=">= 0")
    parser.add_argument("--workers", type=positive_int, default=2, help="processes")
    return parser


def parse_limits_args(
    parser: argparse.ArgumentParser, argv: list[str] | None, min_robots: int
) -> argparse.Namespace:
    """``parser``'s arguments (a ``limits_parser``) with the scenario checked: robots in
    ``min_robots``..MAX_ROBOTS, a duration of at least 8 s, a trajectory for that team."""
    from astrocargo.envs.world import MAX_ROBOTS

    args = parser.parse_args(argv)
    check(
        parser,
        min_robots <= args.robots <= MAX_ROBOTS,
        f"--robots must be {min_robots} to {MAX_ROBOTS}, got {args.robots}",
    )
    check(parser, args.duration >= 8.0, f"--duration must be >= 8 s, got {args.duration}")
    check_trajectory(parser, args.trajectory, args.robots)
    return args
