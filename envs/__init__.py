"""Environments; the TorchRL env suite arrives with the environments issue; for now it ships the MJCF assets."""

import pathlib

ASSETS_DIR = pathlib.Path(__file__).parent / "assets"


def asset_path(name: str) -> pathlib.Path:
    """Return the path of a bundled asset (e.g. ``"ant.xml"``); raise FileNotFoundError if missing."""
    path = ASSETS_DIR / name
    if not path.is_file():
        available = sorted(p.name for p in ASSETS_DIR.iterdir() if p.is_file()) if ASSETS_DIR.is_dir() else []
        raise FileNotFoundError(f"asset {name!r} not found in {ASSETS_DIR}; available: {available}")
    return path
