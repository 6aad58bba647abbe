"""The tables, the seed ablation and the learning-curve figure of ``evaluate.py``'s results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

METRICS = (
    ("return", "return", "{:9.2f}"),
    ("track_pos_m", "pos err m", "{:9.4f}"),
    ("track_att_rad", "att err rad", "{:9.4f}"),
    ("final_pos_m", "end pos m", "{:9.4f}"),
    ("final_att_rad", "end att rad", "{:9.4f}"),
    ("mass_rel_err", "mass err", "{:9.4f}"),
    ("com_err_m", "CoM err m", "{:9.4f}"),
    ("principal_rel_err", "inertia err", "{:9.4f}"),
    ("mass_conv_s", "mass 5% s", "{:9.1f}"),
    ("saturated", "saturated", "{:9.4f}"),
    ("wall_contact", "wall", "{:9.2f}"),
)
BOUND_METRICS = (
    ("bound_principal_rel", "bound I1/I2/I3"),
    ("filter_principal_rel", "filter I1/I2/I3"),
)
CORRECTION_METRICS = (("correction_mean", "correction"), ("correction_p95", "correction p95"))


def _cell(stat: dict, fmt: str) -> str:
    mean, std = np.atleast_1d(stat["mean"]), np.atleast_1d(stat["std"])
    if len(mean) > 1:
        return "/".join(fmt.format(m).strip() for m in mean)
    return f"{fmt.format(mean[0]).strip()} +- {fmt.format(std[0]).strip()}"


def print_table(results: list[dict]) -> None:
    width = max(len(r["policy"]) for r in results) + 14
    bound = [(k, label) for k, label in BOUND_METRICS if k in results[0]["summary"]]
    bound += [(k, label) for k, label in CORRECTION_METRICS if k in results[0]["summary"]]
    print(
        f"{'policy':<{width}}"
        + "".join(f"{label:>20}" for _, label, _ in METRICS)
        + "".join(f"{label:>22}" for _, label in bound)
    )
    for r in results:
        for name, summary in [("all", r["summary"])] + (
            list(r["bins"].items()) if len(r["bins"]) > 1 else []
        ):
            cells = [_cell(summary[key], fmt) for key, _, fmt in METRICS]
            cells += [_cell(summary[key], "{:.3f}") if key in summary else "-" for key, _ in bound]
            print(
                f"{r['policy'] + ' [' + name + ']':<{width}}"
                + "".join(f"{c:>20}" for c in cells[: len(METRICS)])
                + "".join(f"{c:>22}" for c in cells[len(METRICS) :])
            )
    for r in results:
        if r["terminated_episodes"]:
            print(f"{r['policy']}: {r['terminated_episodes']} episodes ended by termination")


ABLATION_METRICS = ("track_pos_m", "track_att_rad", "return")


def arm_key(config: dict) -> str:
    """A run's arm: its configuration without the seed (algorithm, residual scale and base,
    feed-forward input, training length or checkpoint, view, task, estimates observed)."""
    kwargs = config["env_kwargs"]
    residual = kwargs.get("residual_scale", 0.0)
    base = kwargs.get("base_model", "none")
    on = f" on {base}" if base != "none" else ""
    kind = f"{config['algo'].upper()}{f' residual x{residual:g}{on}' if residual else ''}"
    if kwargs.get("feedforward_obs"):
        kind += " + feed-forward input"
    if "imitation" in config:
        kind += ", imitation of the live-estimate controller"
    elif "init_from" in config:
        kind += ", from imitation"
    if "masked_block" in config:
        kind += f", {config['masked_block']} masked"
    if "checkpoint_samples" in config:  # a checkpoint is an arm of its own training length
        kind += f" (checkpoint at {config['checkpoint_samples']} samples)"
    elif config.get("timesteps"):
        kind += f" ({config['timesteps']} samples)"
    obs = "with" if policy_observes_estimates(kwargs) else "without"
    return f"{kind}, {config['view']}, task {config.get('task', '?')}, {obs} estimates"


def policy_observes_estimates(env_kwargs: dict) -> bool:
    """Whether a run's policy saw the estimates (the env observed them and did not hide them)."""
    return bool(env_kwargs["observe_estimates"]) and not env_kwargs.get("hide_estimates", False)


def ablation(results: list[dict]) -> dict:
    """Per arm and mass bin: each seed's mean over the episodes, their mean and standard
    deviation (ddof 1) over seeds; per pair of arms differing only in observing the estimates:
    the difference of the means (with - without) and whether it exceeds the larger of the two
    arms' seed spreads."""
    arms: dict[str, dict] = {}
    for r in results:
        if r["config"] is None:
            continue
        arm = arms.setdefault(
            arm_key(r["config"]), {"seeds": [], "bins": {}, "config": r["config"]}
        )
        arm["seeds"].append(r["config"]["seed"])
        for name, summary in r["bins"].items():
            per = arm["bins"].setdefault(name, {m: [] for m in ABLATION_METRICS})
            for m in ABLATION_METRICS:
                per[m].append(float(np.atleast_1d(summary[m]["mean"])[0]))
    for arm in arms.values():
        for per in arm["bins"].values():
            for m in ABLATION_METRICS:
                values = np.array(per[m])
                spread = float(np.std(values, ddof=1)) if len(values) > 1 else float("nan")
                per[m] = {"per_seed": values.tolist(), "mean": float(values.mean()), "std": spread}
    pairs = []
    for key, arm in arms.items():
        if not policy_observes_estimates(arm["config"]["env_kwargs"]):
            continue
        other = key.replace("with estimates", "without estimates")
        if other not in arms:
            continue
        diffs = {}
        for name, per in arm["bins"].items():
            if name not in arms[other]["bins"]:
                continue
            base = arms[other]["bins"][name]
            diffs[name] = {}
            for m in ABLATION_METRICS:
                diff = per[m]["mean"] - base[m]["mean"]
                spread = max(per[m]["std"], base[m]["std"])
                diffs[name][m] = {
                    "with_minus_without": diff,
                    "seed_spread": spread,
                    "exceeds_spread": bool(abs(diff) > spread) if np.isfinite(spread) else None,
                }
        pairs.append({"with": key, "without": other, "bins": diffs})
    for arm in arms.values():
        del arm["config"]
    return {"arms": arms, "pairs": pairs}


def print_ablation(table: dict) -> None:
    print("\nablation: per mass bin, mean over seeds (seed std; per seed), pos. error mm")
    for key, arm in table["arms"].items():
        print(f"  {key}: seeds {arm['seeds']}")
        for name, per in arm["bins"].items():
            s = per["track_pos_m"]
            seeds = ", ".join(f"{1e3 * v:.1f}" for v in s["per_seed"])
            print(f"    {name:>12}: {1e3 * s['mean']:.1f} ({1e3 * s['std']:.1f}; {seeds})")
    for pair in table["pairs"]:
        print(f"  {pair['with']} minus {pair['without']}:")
        for name, d in pair["bins"].items():
            x = d["track_pos_m"]
            verdict = {True: "exceeds", False: "within", None: "one seed:"}[x["exceeds_spread"]]
            print(
                f"    {name:>12}: {1e3 * x['with_minus_without']:+.1f} mm, {verdict} the seed "
                f"spread {1e3 * x['seed_spread']:.1f} mm"
            )


def plot_curves(curves: dict, baselines: list[dict], path: Path) -> None:
    """Return and mean cargo position error against decisions, with baselines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 5), layout="constrained")
    for (key, label), ax in zip(
        (("return", "return (mean over robots)"), ("track_pos_m", "cargo position error [m]")),
        axes,
        strict=True,
    ):
        for curve in curves.values():
            config = curve["config"]
            robots = config["env_kwargs"]["n_robots"]
            steps = [p["samples"] / robots for p in curve["points"]]
            mean = np.array([p[key]["mean"] for p in curve["points"]], dtype=float)
            std = np.array([p[key]["std"] for p in curve["points"]], dtype=float)
            minutes = config.get("wall_s", float("nan")) / 60
            # The training's wall time goes in the legend: notes at the curves' ends overlap.
            name = f"{arm_key(config)}, seed {config.get('seed', '?')} ({minutes:.0f} min)"
            line = ax.plot(steps, mean, marker="o", ms=3, label=name)[0]
            ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        for base, style in zip(baselines, ("-.", "--", ":"), strict=False):
            ax.axhline(
                base["summary"][key]["mean"], color="k", ls=style, lw=1, label=base["policy"]
            )
        ax.set_xlabel("decisions (samples / robots, all copies together)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, loc="outside lower center", ncols=min(2, len(labels)))
    fig.suptitle(
        "Deterministic policy on the same seeded episodes (mean +- std over episodes; "
        "training wall time in brackets)"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
