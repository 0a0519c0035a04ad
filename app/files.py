"""Where the project's files live, and reading the ones people give us.

The shipped configuration (``static_config/``: default.toml, camera rigs, scenarios) is
package data, found next to the installed code, so a non-editable install runs from any
folder. Sessions are recorded under the working folder's ``recordings/`` unless a command
is told otherwise (``--recordings DIR``). Paths are shown to people relative to the working
folder when they are inside it.

Every reading function here turns a problem with a file into one :class:`UserError` line.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import static_config

if TYPE_CHECKING:
    import numpy as np

    from app.contracts import Rig
    from core.camera.config import CameraConfig
    from core.camera.gamma import Gamma, MatchingTable
    from core.config import Scenario
    from core.fleet import FleetScenario

STATIC_CONFIG = Path(static_config.__file__).resolve().parent
SCENARIOS = STATIC_CONFIG / "scenarios"
FLEETS = STATIC_CONFIG / "fleets"
DEFAULT_CONFIG = STATIC_CONFIG / "default.toml"
CAMERA_DIR = STATIC_CONFIG / "camera"
SYNTHETIC_CAMERA = CAMERA_DIR / "synthetic.toml"
# Γ of the built-in synthetic rig, made by `omniformation calibrate --synthetic` (see README)
SYNTHETIC_CALIBRATED = CAMERA_DIR / "synthetic_calibrated.toml"


class UserError(Exception):
    """A mistake in what a person gave us (file, argument, value): one line, exit code 2."""


def bind_error(host: str, port: int, exc: OSError) -> str:
    """One line for a server that could not bind."""
    import errno
    import os

    why = os.strerror(exc.errno) if exc.errno else str(exc)
    if exc.errno == errno.EADDRINUSE:
        why += " (another program, perhaps another omniformation, serves there: stop it or give another --port)"
    elif exc.errno == errno.EADDRNOTAVAIL:
        why += " (this machine has no such address: give one of its own, 127.0.0.1, or 0.0.0.0 for all)"
    return f"cannot serve on {host}:{port}: {why}"


def default_recordings() -> Path:
    """The folder sessions are recorded to and listed from: ``recordings/`` under the working folder."""
    return Path.cwd() / "recordings"


def display_path(path: Path) -> str:
    """A path as people should see it: relative to the working folder when inside it."""
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except (ValueError, OSError):
        return str(path)


def check_out_path(path: Path) -> None:
    """A file we are about to write: its folder must exist."""
    if not path.parent.exists():
        raise UserError(f"{path}: folder {path.parent} does not exist")


def prepare_out_dir(out: Path) -> None:
    """A folder we are about to write files into: made if missing, and shown to be writable;
    one line naming what is wrong otherwise."""
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".omniformation-write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UserError(f"{out}: cannot write there: {exc.strerror or exc}") from None


def check_new_file(path: Path, what: str, *suffixes: str) -> None:
    """A file we are about to write: not a folder, its folder exists and is writable, and (if
    given) one of ``suffixes``; one line naming what is wrong otherwise."""
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give a file name for the {what}")
    if suffixes and path.suffix.lower() not in suffixes:
        raise UserError(f"{path}: the {what} must be a {' or '.join(suffixes)} file")
    check_out_path(path)
    import os

    if not os.access(path.parent, os.W_OK):
        raise UserError(f"{path}: folder {path.parent} is not writable")
    if path.exists() and not path.is_file():
        raise UserError(f"{path}: exists and is not a regular file")


def read_text(path: Path, what: str) -> str:
    """A text file people named, as text; a missing or unreadable one is one line."""
    if not path.is_file():
        raise UserError(f"{path}: no such {what} file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{display_path(path)}: cannot read: {exc}") from None


KEY_FILE_LIMIT = 64 * 1024  # a key, a certificate, a roster or a counter is far smaller


def read_regular(path: Path, what: str, limit: int = KEY_FILE_LIMIT) -> bytes:
    """The bytes of a small file people named (a key, a certificate, a counter): read only if it
    is a regular file (a FIFO would hang the reader, /dev/zero fill its memory, a folder is not
    one) and at most ``limit`` bytes long. A missing file is FileNotFoundError (the caller says
    what writes it); anything else is one UserError line naming the file."""
    import os
    import stat

    try:  # O_NONBLOCK: opening a FIFO with no writer must not wait for one
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise UserError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = ("a folder" if stat.S_ISDIR(st.st_mode) else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                    else "a device" if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                    else "a socket" if stat.S_ISSOCK(st.st_mode) else "not a regular file")
            raise UserError(f"{path}: is {kind}; {what} must be a regular file")
        if st.st_size > limit:
            raise UserError(f"{path}: {st.st_size} bytes; {what} is at most {limit} bytes (is it the right file?)")
        chunks, size = [], 0
        while size <= limit:  # a file that grows while read stops at the limit too
            chunk = os.read(fd, limit + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > limit:
            raise UserError(f"{path}: more than {limit} bytes; {what} is at most {limit} bytes (is it the right file?)")
        return b"".join(chunks)
    except OSError as exc:
        raise UserError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    finally:
        os.close(fd)


def parse_json(data: bytes, path: Path, what: str) -> object:
    """``data`` as JSON; not JSON, not UTF-8 or nested too deep for the parser (a hostile file:
    thousands of ``[``) is one UserError line naming ``path``."""
    import json

    try:
        return json.loads(data)
    except RecursionError:
        raise UserError(f"{path}: not {what} (nested too deep)") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not {what} ({exc})") from None


# ---------------------------------------------------------------- scenarios


def scenario_names(folder: Path = SCENARIOS) -> list[str]:
    return sorted(p.stem for p in folder.glob("*.toml"))


def resolve_scenario_path(name_or_path: str, folder: Path = SCENARIOS, what: str = "scenario") -> Path:
    """A path as given, or a bare name from the shipped scenarios (or fleets)."""
    as_path = Path(name_or_path)
    if as_path.suffix == ".toml" or "/" in name_or_path or as_path.exists():
        if not as_path.is_file():
            raise UserError(f"{name_or_path}: no such {what} file")
        return as_path
    candidate = folder / f"{name_or_path}.toml"
    if not candidate.is_file():
        raise UserError(
            f"{what} {name_or_path!r} not found: give a .toml path or one of {', '.join(scenario_names(folder))}"
        )
    return candidate


def load_fleet(name_or_path: str) -> FleetScenario:
    """Read and validate a fleet scenario (static_config/fleets/); any problem is one line."""
    from core.config import ConfigError
    from core.fleet import parse_fleet

    path = resolve_scenario_path(name_or_path, FLEETS, "fleet scenario")
    try:
        return parse_fleet(read_text(path, "fleet scenario"), display_path(path))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:
        raise UserError(f"{display_path(path)}: {exc}") from None


def load_scenario(name_or_path: str) -> Scenario:
    """Read and validate a scenario; any problem is a one-line UserError."""
    from core.config import ConfigError, parse_scenario

    path = resolve_scenario_path(name_or_path)
    text = read_text(path, "scenario")
    try:
        return parse_scenario(text, display_path(path))
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    except ValueError as exc:  # a Gains / dataclass check that names key and range itself
        raise UserError(f"{display_path(path)}: {exc}") from None


# ---------------------------------------------------------------- camera rigs and tables


def load_camera(path: Path) -> CameraConfig:
    from core.camera.config import parse_camera
    from core.camera.gamma import CalibrationError
    from core.config import ConfigError

    try:
        return parse_camera(read_text(path, "camera config"), display_path(path))
    except (ConfigError, CalibrationError) as exc:
        raise UserError(str(exc)) from None


def require_gamma(cfg: CameraConfig) -> Gamma:
    """``cfg.require_gamma()`` with its one-line message as a UserError."""
    from core.config import ConfigError

    try:
        return cfg.require_gamma()
    except ConfigError as exc:
        raise UserError(str(exc)) from None


def load_calibration(path: Path) -> Rig:
    """A rig's calibration file (working area, detection, Γ) and its Γ; one-line UserError without Γ."""
    from app.contracts import Rig

    cfg = load_camera(path)
    return Rig(cfg, require_gamma(cfg))


def load_synthetic_rig(rig_path: Path, calibration_path: Path) -> Rig:
    """A synthetic rig that renders frames and the Γ that reads them, each checked (one-line UserError)."""
    from app.contracts import Rig

    rig = load_camera(rig_path)
    if rig.model is None:
        raise UserError(f"{display_path(rig_path)}: has no [model]: a synthetic rig is needed to render frames")
    return Rig(rig, load_calibration(calibration_path).gamma)


def load_table(path: Path) -> MatchingTable:
    from core.camera.gamma import CalibrationError, parse_table

    try:
        return parse_table(read_text(path, "matching table"), display_path(path))
    except CalibrationError as exc:
        raise UserError(str(exc)) from None


def write_table(table: MatchingTable, path: Path) -> None:
    lines = ["bearing_deg,metres,u,v"]
    lines += [f"{b:g},{d:g},{u:.3f},{v:.3f}" for b, d, u, v in zip(table.bearing_deg, table.metres, table.u, table.v)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def read_image(path: Path) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise UserError(f"{path}: no such image file")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise UserError(f"{display_path(path)}: not an image OpenCV can read (PNG, JPEG, BMP, ...)")
    return img
