"""Where the project's own files live (static_config/, recordings/), relative to the checkout."""

from __future__ import annotations

from pathlib import Path

PROJECT_ROOT = Path(__file__).resolve().parent.parent
STATIC_CONFIG = PROJECT_ROOT / "static_config"
SCENARIOS = STATIC_CONFIG / "scenarios"
RECORDINGS = PROJECT_ROOT / "recordings"
DEFAULT_CONFIG = STATIC_CONFIG / "default.toml"
CAMERA_DIR = STATIC_CONFIG / "camera"
SYNTHETIC_CAMERA = CAMERA_DIR / "synthetic.toml"
# Γ of the built-in synthetic rig, made by `omniformation calibrate --synthetic` (see README)
SYNTHETIC_CALIBRATED = CAMERA_DIR / "synthetic_calibrated.toml"


class UserError(Exception):
    """A mistake in what a person gave us (file, argument, value): one line, exit code 2."""


def scenario_names() -> list[str]:
    return sorted(p.stem for p in SCENARIOS.glob("*.toml"))


def resolve_scenario_path(name_or_path: str) -> Path:
    """A path as given, or a bare name from static_config/scenarios."""
    as_path = Path(name_or_path)
    if as_path.suffix == ".toml" or "/" in name_or_path or as_path.exists():
        if not as_path.is_file():
            raise UserError(f"{name_or_path}: no such scenario file")
        return as_path
    candidate = SCENARIOS / f"{name_or_path}.toml"
    if not candidate.is_file():
        raise UserError(
            f"scenario {name_or_path!r} not found: give a .toml path or one of {', '.join(scenario_names())}"
        )
    return candidate


def display_path(path: Path) -> str:
    """A path as people should see it: relative to the checkout when inside it."""
    try:
        return str(path.resolve().relative_to(PROJECT_ROOT))
    except ValueError:
        return str(path)
