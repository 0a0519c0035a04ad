"""The calibration page: from an empty table to a saved camera file, in the browser.

The live camera (a device, a video, a folder, or the synthetic rig) is shown with the
mirror's centre and the working area drawn on it. "Propose from image" finds the mirror's
circle (core.camera.guide.find_mirror_rim: from its edges); the centre and the working area's radii stay
adjustable by dragging their sliders. How the camera is turned and mirrored is read from
the markers (core.camera.quality.detect_mounting). The guide names the next marker's bearing and distance
(4 bearings x 7 distances, from the working ring's inner edge out); the operator puts a marker there, confirms or corrects the
bearing and distance, and presses Capture: the marker is found in the picture (exactly one,
inside the working area, or the capture is refused saying why) and its pixel joins the table.
From enough markers on, Γ is fitted after every capture (core.camera.gamma), with its
held-out error and coverage warnings (core.camera.quality) and a figure of the coverage
and the per-sector residuals. Save writes the camera TOML and the table's CSV (never over a
file unless "Overwrite" is ticked); Load reads a table (CSV) or a camera file (its centre and
working area).
"""

from __future__ import annotations

import html
import math
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import viser

from core.camera.config import DetectSettings, WorkingArea, gamma_toml
from core.camera.gamma import CalibrationError, GammaFit, MatchingTable, estimate_center, fit_gamma
from core.camera.guide import find_marker, find_mirror_rim, guide_targets, next_target
from core.camera.quality import HeldOut, coverage_warnings, detect_mounting, held_out_error

from app.contracts import FrameSource
from app.dashboard.widgets import assign, on_page_thread

DEGREE = 3
PREVIEW_WIDTH = 480
PICTURE_SHARE = 0.68  # of the main view's width the picture is centred in (the panel floats over the rest)
GOOD_P95_CM = 2.0  # held-out p95 at or under this: good, save
USABLE_P95_CM = 3.0  # under this: usable (the page's promise); above: capture more before saving
STEPS = ("1. **Find the mirror**: press *Propose from image* (or drag the centre and radii sliders until the"
         " circles sit on the mirror).",
         "2. **Put a marker** where *Next marker* says (bearing 0–360°, 0 ahead, counter-clockwise; distance from"
         " the camera's axis); correct the bearing and distance if it stands elsewhere.",
         "3. **Capture**. Repeat 2–3 until the guide's plan is done; the fit and its verdict follow every capture.",
         "4. **Save** when the verdict says good (or do what it says first).")


def verdict(held: HeldOut | None, warnings: list[str]) -> tuple[str, str]:
    """(word, sentence) for a fit: good (save), usable (save, or capture more) or poor (what to do)."""
    if held is None:
        return "none", "no fit yet: capture markers where the guide says"
    p95 = f"p95 {held.p95_cm:.1f} cm"
    if held.p95_cm <= GOOD_P95_CM and not warnings:
        return "good", f"{p95}: good, Save"
    if held.p95_cm <= USABLE_P95_CM:
        todo = "fill the gaps the warnings name, then Save" if warnings else "Save, or capture more markers near the worst sector"
        return "usable", f"{p95}: usable; {todo}"
    return "poor", (f"{p95}: not good enough (over {USABLE_P95_CM:g} cm): capture more markers, most where the"
                    " sector table shows the largest error" + ("; fill the gaps the warnings name" if warnings else ""))


class CalibrationPanel:
    def __init__(self, server: viser.ViserServer, source: FrameSource, detect: DetectSettings,
                 save_as: Path, centre: tuple[float, float] | None = None,
                 area: WorkingArea | None = None) -> None:
        self.server = server
        self.source = source
        self.detect = detect
        self.targets = guide_targets()
        self.rows: list[tuple[float, float, float, float]] = []  # bearing deg, metres, u, v
        self.fit: GammaFit | None = None
        self.held: HeldOut | None = None
        self.warnings: list[str] = []
        self.fitted = 0  # markers the fit shown was made from
        self.annotated: np.ndarray | None = None  # the last preview at full size (BGR)
        self.message = ""
        self._lock = threading.Lock()
        self._busy = threading.Lock()
        self.clicks = 0  # Capture clicks received; each ends in one capture or one refusal, in order
        self._waiting = 0  # clicks not yet done
        frame = source.latest()[0]
        h, w = (frame.shape[:2] if frame is not None else (480, 640))
        cx, cy = centre if centre is not None else (w / 2, h / 2)
        area = area or WorkingArea(0.2 * min(w, h) / 2, 0.8 * min(w, h) / 2)
        gui = server.gui
        with gui.add_folder("Calibration"):
            self.steps = gui.add_markdown("\n".join(STEPS))
            self.preview = gui.add_image(np.zeros((8, 8, 3), np.uint8), label="camera", format="jpeg")
            self.propose = gui.add_button("Propose from image", hint="find the mirror's circle in the picture")
            reach = round(math.hypot(w, h) / 2)  # drag the sliders: the preview draws what they say
            self.cx = gui.add_slider("Centre x (px)", min=0.0, max=float(w), step=0.5,
                                     initial_value=min(float(w), max(0.0, round(cx, 1))))
            self.cy = gui.add_slider("Centre y (px)", min=0.0, max=float(h), step=0.5,
                                     initial_value=min(float(h), max(0.0, round(cy, 1))))
            self.inner = gui.add_slider("Area inner (px)", min=0.0, max=float(reach), step=1.0,
                                        initial_value=min(float(reach), round(area.inner_px, 1)))
            self.outer = gui.add_slider("Area outer (px)", min=1.0, max=float(reach), step=1.0,
                                        initial_value=min(float(reach), round(area.outer_px, 1)))
            self.guide = gui.add_markdown("")
            self.bearing = gui.add_number("Marker bearing (°, 0–360)", initial_value=0.0, step=1.0, min=0.0, max=360.0,
                                          hint="0 ahead, counter-clockwise, 0 to 360° (360 is 0)")
            self.distance = gui.add_number("Marker distance (m)", initial_value=0.5, step=0.01, min=0.05, max=10.0)
            self.capture = gui.add_button("Capture", hint="find the marker in the picture and add it to the table;"
                                                          " clicks made while one runs wait their turn")
            self.busy = gui.add_markdown("")
            self.undo = gui.add_button("Undo last capture", color="gray")
            self.status = gui.add_markdown("")
            self.quality = gui.add_html("")
            self.figure = gui.add_image(np.full((8, 8, 3), 255, np.uint8), format="png", visible=False)
            self.save_as = gui.add_text("Save as", initial_value=str(save_as))
            self.overwrite = gui.add_checkbox("Overwrite", initial_value=False)
            self.save = gui.add_button("Save camera file and table")
            self.load_from = gui.add_text("Load from", initial_value="")
            self.load = gui.add_button("Load", hint="a table (.csv) to go on from, or a camera file (.toml): its"
                                                   " centre and working area")
        self._wire()
        self.show_next()

    # -- what the operator does -----------------------------------------------------------
    def propose_circle(self) -> str:
        frame = self.source.latest()[0]
        if frame is None:
            return self._say("no picture from the camera yet")
        c = find_mirror_rim(frame)
        if c is None:
            return self._say("no mirror circle found in the picture: set the centre and radii by hand")
        assign(self.cx, round(c.cx, 1))
        assign(self.cy, round(c.cy, 1))
        assign(self.inner, round(0.22 * c.radius, 1))  # the leader's own body hides the middle
        assign(self.outer, round(0.8 * c.radius, 1))  # the floor ends before the rim (walls, sky)
        return self._say(f"mirror circle: centre ({c.cx:.1f}, {c.cy:.1f}) px, radius {c.radius:.1f} px;"
                         f" working area {0.22 * c.radius:.0f}..{0.8 * c.radius:.0f} px (adjust if needed)")

    def capture_marker(self) -> str:
        """One click: queued behind any capture running (none is dropped), the wait shown."""
        with self._lock:
            self.clicks += 1
            self._waiting += 1
        self._show_busy()
        try:
            with self._busy:  # one capture at a time: a second click waits for the first to finish
                return self._capture()
        finally:
            with self._lock:
                self._waiting -= 1
            self._show_busy()

    def _show_busy(self) -> None:
        n = self._waiting
        self.busy.content = ("" if n <= 0 else "**capturing…**" if n == 1
                             else f"**capturing…** ({n - 1} more {'click' if n == 2 else 'clicks'} waiting)")

    def _capture(self) -> str:
        frame = self.source.latest()[0]
        if frame is None:
            return self._say("no picture from the camera yet")
        b, d = float(self.bearing.value), float(self.distance.value)
        if not (math.isfinite(b) and math.isfinite(d) and d > 0 and 0.0 <= b <= 360.0):
            return self._say(f"bearing {b!r}° and distance {d!r} m: give a bearing from 0 to 360° and a distance"
                             " over 0 m")
        b = guide_deg(b)
        inner, outer = float(self.inner.value), float(self.outer.value)
        if not (math.isfinite(inner) and math.isfinite(outer) and 0 <= inner < outer):
            return self._say(f"working area {inner!r}..{outer!r} px: the inner radius must be under the outer")
        area = WorkingArea(inner, outer)
        found = find_marker(frame, (float(self.cx.value), float(self.cy.value)), area, self.detect)
        if isinstance(found, str):
            return self._say(f"capture refused: {found}")
        with self._lock:
            same = [k for k, r in enumerate(self.rows) if abs((r[0] - b + 180) % 360 - 180) < 1e-6 and abs(r[1] - d) < 1e-6]
            if same:
                return self._say(f"capture refused: row {same[0] + 1} already has a marker at {b:g}°, {d:g} m;"
                                 " undo it or give another bearing or distance")
            self.rows.append((b % 360.0, d, found.u, found.v))
        self.show_next()
        said = self._say(f"captured {len(self.rows)}: {b:g}°, {d:g} m at pixel ({found.u:.1f}, {found.v:.1f})")
        self._refit()
        return said

    def undo_last(self) -> str:
        with self._lock:
            if not self.rows:
                return self._say("nothing to undo")
            b, d, _, _ = self.rows.pop()
        self._refit()
        self.show_next()
        return self._say(f"removed the capture at {b:g}°, {d:g} m")

    def save_files(self) -> str:
        if self.fit is None:
            return self._say("nothing to save yet: capture markers until the fit is made")
        path = Path(str(self.save_as.value)).expanduser()
        if path.suffix.lower() != ".toml":
            return self._say(f"save as {path}: a camera file is a .toml")
        table_path = path.with_suffix(".csv")
        for target in (path, table_path):
            if target.exists() and not self.overwrite.value:
                return self._say(f"{target} exists: tick Overwrite to replace it, or give another name")
        if not path.parent.is_dir():
            return self._say(f"save as {path}: folder {path.parent} does not exist")
        area = WorkingArea(float(self.inner.value), float(self.outer.value))
        held = self.held
        header = (f"Camera calibration (Γ, paper §3) made on the calibration page from {len(self.rows)} markers\n"
                  f"{self.fit.gamma.n_sectors} sectors, degree {self.fit.gamma.degree}"
                  + (f"; held-out error median {held.median_cm:.2f} cm, p95 {held.p95_cm:.2f} cm" if held else "")
                  + "".join(f"\nwarning: {w}" for w in self.warnings))
        from app.files import write_table
        from core.camera.lighting import measure_lighting

        frame = self.source.latest()[0]  # the light the rig was calibrated in, for the live monitor
        light = measure_lighting(frame, (self.fit.gamma.cx, self.fit.gamma.cy), area) if frame is not None else None
        try:
            path.write_text(gamma_toml(self.fit.gamma, area, self.detect, header,
                                       None if light is None else (light.value, light.cast_bg, light.cast_rg)),
                            encoding="utf-8")
            write_table(self.table(), table_path)
        except OSError as exc:
            return self._say(f"save as {path}: {exc.strerror or exc}")
        return self._say(f"saved {path} and {table_path.name}")

    def load_file(self) -> str:
        path = Path(str(self.load_from.value)).expanduser()
        from app.files import UserError, load_camera, load_table

        try:
            if path.suffix.lower() == ".csv":
                t = load_table(path)
                with self._lock:
                    self.rows = [(float(b) % 360.0, float(d), float(u), float(v))
                                 for b, d, u, v in zip(t.bearing_deg, t.metres, t.u, t.v)]
                self._refit()
                self.show_next()
                return self._say(f"loaded {count_markers(len(self.rows))} from {path}")
            if path.suffix.lower() == ".toml":
                cam = load_camera(path)
                g = cam.gamma
                if g is not None:
                    assign(self.cx, round(g.cx, 1))
                    assign(self.cy, round(g.cy, 1))
                assign(self.inner, cam.working_area.inner_px)
                assign(self.outer, cam.working_area.outer_px)
                return self._say(f"loaded the centre and working area of {path}")
        except UserError as exc:
            return self._say(f"load: {exc}")
        return self._say(f"load {path}: a table (.csv) or a camera file (.toml)")

    # -- what follows ---------------------------------------------------------------------
    def table(self) -> MatchingTable:
        a = np.array(self.rows, dtype=np.float64).reshape(-1, 4)
        return MatchingTable(a[:, 0], a[:, 1], a[:, 2], a[:, 3])

    def _refit(self) -> None:
        """Fit Γ to the table as it is now; ``fitted`` says how many markers the shown fit used."""
        n = len(self.rows)
        if n < 6:
            self.fit, self.held, self.warnings, self.fitted = None, None, [], n
            self._show_quality(f"{count_markers(n)}: the fit needs at least 6, and {DEGREE + 2} at each bearing it"
                               f" uses; {self._per_bearing()}")
            return
        table = self.table()
        flip, offset = False, 0.0
        mount = detect_mounting(table, estimate_center(table))  # a camera mounted turned or mirrored
        if mount is not None and mount.certain:
            flip, offset = mount.flip, round(mount.offset_deg, 1)
        try:
            fit = fit_gamma(table, degree=DEGREE, source="the captures", flip=flip, bearing_offset_deg=offset)
        except CalibrationError as exc:
            self.fit, self.held, self.warnings, self.fitted = None, None, [], n
            self._show_quality(f"not fitted yet: {exc}; {self._per_bearing()}")
            return
        held = held_out_error(table, fit.gamma, fit.gamma.degree)
        warnings = coverage_warnings(table)
        if held.p95_cm > 3.0:
            warnings.insert(0, f"positions may be off by more than 3 cm (held-out p95 {held.p95_cm:.1f} cm):"
                               " capture more markers")
        self.fit, self.held, self.warnings, self.fitted = fit, held, warnings, n
        rows = "".join(f"<tr><td>{guide_deg(s.bearing_deg):g}</td><td>{s.points}</td><td>{s.rms_cm:.2f}</td>"
                       f"<td>{s.max_cm:.2f}</td></tr>" for s in fit.sectors)
        mounted = (f"<div>the camera is turned by {offset % 360.0:.1f}°{' and mirrored' if flip else ''} (read from"
                   " the markers)</div>") if (flip or offset) else ""
        word, sentence = verdict(held, warnings)
        colour = {"good": "#1a7f37", "usable": "#9a6700"}.get(word, "#cf222e")
        text = (f"<div data-verdict='{word}' style='font-size:15px;font-weight:bold;color:{colour}'>"
                f"{html.escape(sentence)}</div>"
                f"<div data-held-out='{held.p95_cm:.3f}'>held-out error: median {held.median_cm:.2f} cm,"
                f" p95 {held.p95_cm:.2f} cm</div>" + mounted
                + "".join(f"<div style='color:#b35900'>warning: {html.escape(w)}</div>" for w in warnings)
                + "<table style='font-size:11px'><tr><th>sector (°, 0–360)</th><th>markers</th><th>RMS (cm)</th>"
                  "<th>max (cm)</th></tr>" + rows + "</table>")
        self.quality.content = text
        self._draw_figure()

    def _per_bearing(self) -> str:
        """How many markers each bearing has against what the fit needs there (the guide's names)."""
        counts: dict[float, int] = {}
        for b, *_ in self.rows:
            key = guide_deg(b)
            counts[key] = counts.get(key, 0) + 1
        if not counts:
            return "none captured yet"
        return "so far " + ", ".join(f"{b:g}°: {c}/{DEGREE + 2}" for b, c in sorted(counts.items()))

    def _show_quality(self, text: str) -> None:
        self.quality.content = f"<div>{html.escape(text)}</div>"
        self.figure.visible = False

    def _draw_figure(self) -> None:
        from matplotlib.figure import Figure

        from app.figures import figure_rgb

        assert self.fit is not None
        fig = Figure(figsize=(6.4, 3.4), constrained_layout=True)
        ax: Any = fig.add_subplot(1, 2, 1, projection="polar")
        ax.set_theta_zero_location("N")
        tb = np.radians([t[0] for t in self.targets])
        ax.scatter(tb, [t[1] for t in self.targets], s=14, facecolors="none", edgecolors="0.6")
        ax.scatter(np.radians([r[0] for r in self.rows]), [r[1] for r in self.rows], s=10, color="tab:blue")
        ax.set_title("coverage", fontsize=8)
        ax.tick_params(labelsize=6)
        bx = fig.add_subplot(1, 2, 2)
        sectors = self.fit.sectors
        bx.bar([f"{guide_deg(s.bearing_deg):g}" for s in sectors], [s.rms_cm for s in sectors], color="tab:blue")
        bx.set_xlabel("sector (°, 0–360, as the guide names bearings)", fontsize=7)
        if self.held is not None:
            bx.axhline(self.held.p95_cm, color="tab:red", ls="--", lw=0.8, label="held-out p95")
            bx.legend(fontsize=6)
        bx.set_title("residual RMS per sector (cm)", fontsize=8)
        bx.tick_params(labelsize=6)
        self.figure.image = figure_rgb(fig)
        self.figure.visible = True

    def show_next(self) -> None:
        """Ask for the next marker (the synthetic rig's helper puts it there)."""
        target = next_target(self.targets, [(r[0], r[1]) for r in self.rows])
        done = len(self.rows)
        if target is None:
            self.guide.content = (f"**{count_markers(done)} captured**: the guide's {len(self.targets)} are done;"
                                  " more anywhere help.")
            return
        b, d = target
        self.guide.content = (f"**Next marker ({done + 1} of {len(self.targets)})**: bearing {b:g}° (0 ahead,"
                              f" counter-clockwise), {d:g} m from the camera's axis")
        assign(self.bearing, b)
        assign(self.distance, d)
        place = getattr(self.source, "place", None)
        if callable(place):  # the synthetic rig's helper puts the marker where the guide asks
            place([target])

    def _say(self, text: str) -> str:
        self.message = text
        self.status.content = html.escape(text)
        return text

    def refresh(self) -> None:
        """Redraw the preview: the picture, the mirror's centre, the working area, the target's direction."""
        frame = self.source.latest()[0]
        if frame is None:
            return
        img = np.ascontiguousarray(frame).copy()
        c = (int(round(float(self.cx.value))), int(round(float(self.cy.value))))
        for r in (float(self.inner.value), float(self.outer.value)):
            if r > 0:
                cv2.circle(img, c, int(round(r)), (0, 200, 255), 1, cv2.LINE_AA)
        cv2.drawMarker(img, c, (0, 0, 255), cv2.MARKER_CROSS, 12, 1)
        for _, _, u, v in self.rows:
            cv2.circle(img, (int(round(u)), int(round(v))), 3, (255, 120, 0), -1)
        self.annotated = img  # full size, for the page alone's main view (CalibrationService)
        scale = PREVIEW_WIDTH / img.shape[1]
        if scale < 1:
            img = cv2.resize(img, (PREVIEW_WIDTH, int(img.shape[0] * scale)), interpolation=cv2.INTER_AREA)
        self.preview.image = img[..., ::-1]  # viser takes RGB

    def _wire(self) -> None:
        for button, action in ((self.propose, self.propose_circle), (self.capture, self.capture_marker),
                               (self.undo, self.undo_last), (self.save, self.save_files), (self.load, self.load_file)):
            def handler(event: viser.GuiEvent[Any], action: Any = action) -> None:
                action()

            button.on_click(handler)


class CalibrationService:
    """``omniformation calibrate --page``: the calibration page alone, for a rig (no robots)."""

    def __init__(self, source: FrameSource, detect: DetectSettings, save_as: Path, host: str = "127.0.0.1",
                 port: int = 8080, token: str | None = None) -> None:
        from app.dashboard.gate import serve_gated

        self.source = source
        self.server, self.gate = serve_gated(host, port, token)
        self.server.gui.configure_theme(control_width="large", dark_mode=False)
        self.panel = CalibrationPanel(self.server, source, detect, save_as)
        self.aspect = math.nan  # the main view's width / height the picture was last letterboxed to
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="omniformation-calibration", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return self.gate.url

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            try:
                on_page_thread(self.server, self._draw)  # widgets.on_page_thread says why
            except Exception:  # noqa: BLE001 - a picture that cannot be drawn must not end the page
                pass

    def _draw(self) -> None:
        """The panel's preview, and the same picture as the page's main view: the whole window
        beside the panel (more than half its width), letterboxed to the browser's view so it is
        not stretched."""
        self.panel.refresh()
        img = self.panel.annotated
        if img is None:
            return
        clients = list(self.server.get_clients().values())
        cam = clients[0].camera if clients else None
        aspect = cam.image_width / cam.image_height if cam is not None and cam.image_height > 0 else 1.6
        self.aspect = aspect
        self.server.scene.set_background_image(letterbox(img, aspect)[..., ::-1], format="jpeg", jpeg_quality=85)

    def stop(self) -> None:
        self._stop.set()

    def wait(self) -> None:
        while not self._stop.wait(0.2):
            pass

    def close(self) -> None:
        from app.dashboard.gate import quietly

        self._stop.set()
        self._thread.join(5)
        self.gate.close()
        quietly(self.server.stop)
        self.source.close()


def letterbox(img: np.ndarray, aspect: float, left: float = PICTURE_SHARE) -> np.ndarray:
    """``img`` on a dark canvas of width / height ``aspect`` (a background is stretched to the view),
    centred in the canvas's ``left`` share: the panel floats over the rest."""
    h, w = img.shape[:2]
    if not math.isfinite(aspect) or aspect <= 0:
        return img
    cw = max(round(w / left), round(h * aspect))
    ch = max(h, round(cw / aspect))
    cw = max(cw, round(ch * aspect))
    out = np.full((ch, cw, 3), 30, np.uint8)
    y0, x0 = (ch - h) // 2, max(0, round(cw * left / 2 - w / 2))
    out[y0:y0 + h, x0:x0 + w] = img
    return out


def count_markers(n: int) -> str:
    return f"{n} marker" if n == 1 else f"{n} markers"


def guide_deg(bearing_deg: float) -> float:
    """A sector's bearing as the guide names bearings: 0 to 360 degrees (not -180 to 180)."""
    return round(bearing_deg % 360.0, 6) % 360.0
