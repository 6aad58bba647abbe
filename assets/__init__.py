"""MJCF assets of astrocargo; ``ASSETS_DIR`` is where the XML files live once installed."""

from pathlib import Path

ASSETS_DIR = Path(__file__).resolve().parent
