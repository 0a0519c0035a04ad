"""Loading scenario files for the CLI and the service (file I/O around core.config)."""

from __future__ import annotations

from core.config import ConfigError, Scenario, parse_scenario

from app.paths import UserError, display_path, resolve_scenario_path


def load_scenario(name_or_path: str) -> Scenario:
    """Read and validate a scenario; any problem is a one-line UserError."""
    path = resolve_scenario_path(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{display_path(path)}: cannot read: {exc}") from None
    try:
        return parse_scenario(text, display_path(path))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:  # a Gains / dataclass check that names key and range itself
        raise UserError(f"{display_path(path)}: {exc}") from None
