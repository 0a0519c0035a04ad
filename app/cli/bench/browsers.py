"""The live loop's rate with browsers watching, and the low-priority viewer pages other benches attach."""

from __future__ import annotations

from collections.abc import Callable
from app.cli.bench.family import Family


def bench_loop_with_browsers(seconds: float = 6.0, browsers: int = 3) -> tuple[float, float, float] | None:
    """Achieved loop rate (Hz) with no browser, serving ``browsers`` Chromium pages that render
    at low priority, and with the same pages rendering beside the loop at normal priority.

    Returns None when Debian's chromium or Playwright is not installed.
    """
    import shutil
    import time as _time

    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if chromium is None:
        return None
    from app.services.live import Service

    def measure(svc: Service) -> float:
        start_tick, start = svc.loop.tick_count, _time.monotonic()
        _time.sleep(seconds)
        return (svc.loop.tick_count - start_tick) / (_time.monotonic() - start)

    from app.params import MAX_FOLLOWERS
    from app.live.config import DEFAULT_CONFIG, load_service_config

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)  # what `make run` serves: vision in the loop
    svc = Service(host="127.0.0.1", port=0, n_followers=3, rate_hz=30.0, camera=config.camera(),
                  dynamics=config.dynamics)
    svc.start()
    try:
        _time.sleep(3.0)  # past the first ticks, which load compiled code
        alone = measure(svc)
        # The browsers as if on the operators' own machines (VIEWER), so the figure is what
        # serving them costs the loop.
        import subprocess
        import sys

        viewer = subprocess.Popen([sys.executable, "-c", VIEWER, chromium, svc.url, str(browsers)],
                                  stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            ready = viewer.stdout.readline() if viewer.stdout else ""
            if "ready" not in ready:
                raise RuntimeError(f"the low-priority browsers did not come up: {ready.strip()!r}")
            served = measure(svc)
        finally:
            if viewer.stdin:
                viewer.stdin.close()
            viewer.wait(60)
        with sync_playwright() as p:  # and the same pages rendered beside the loop on this machine
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            # One context (window) each: a background tab in a shared window is throttled.
            pages = [browser.new_context().new_page() for _ in range(browsers)]
            for page in pages:
                page.goto(svc.url)
                page.wait_for_selector(".uplot", state="attached", timeout=90_000)
            watched = measure(svc)
            browser.close()
    finally:
        svc.close()
    return alone, served, watched


# Chromium pages as if on the operators' own machines: the same pages and websocket traffic,
# their (software-WebGL) rendering on this machine's idle CPU only. `nice` does not hold: Chromium
# run as root sets its compositor and IO threads back to nice -8, ahead of the loop. SCHED_IDLE
# (sched(7)) is inherited by every process and thread the browser starts, and their
# setpriority() calls change only a nice value that SCHED_IDLE ignores. SCHED_IDLE alone does not
# hold either where the kernel groups processes by session (autogroup, sched(7)): Playwright starts
# Chromium in a session of its own, and the kernel shares CPU between autogroups as equals whatever
# their tasks' policies (measured: the loop then waited up to 10 ms behind Chromium's threads, p99
# 15-20 ms against 5-6). The browser's autogroup is set to nice 19 as well (any user may lower their
# own autogroup's priority): idle CPU is what it gets.
VIEWER = """
import os, sys
idle = (sys.argv[5] if len(sys.argv) > 5 else "") != "equal"  # "equal": a browser beside the service on a desktop
if idle:
    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))

def descendants():
    # every process this viewer started (Playwright's driver, Chromium and its helpers)
    parents = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            parents[int(pid)] = int(open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
    mine, grew = {os.getpid()}, True
    while grew:
        more = {pid for pid, parent in parents.items() if parent in mine} - mine
        mine |= more
        grew = bool(more)
    return mine - {os.getpid()}

def idle_autogroups():
    # each of them whose autogroup is not ours: nice 19
    try:
        ours = open("/proc/self/autogroup").read().split()[0]
    except OSError:  # no autogroups on this kernel: SCHED_IDLE holds alone
        return
    for pid in descendants():
        try:
            if open(f"/proc/{pid}/autogroup").read().split()[0] != ours:
                open(f"/proc/{pid}/autogroup", "w").write("19")
        except OSError:
            continue

from playwright.sync_api import sync_playwright
chromium, url, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
# the CPUs it may use (argv 4, e.g. "0": kept off a CPU `run --reserve-cpu` keeps); else every one,
# as an operator's browser has (not the bench's own, which a kept CPU may have narrowed)
cpus = sys.argv[4] if len(sys.argv) > 4 else ""
os.sched_setaffinity(0, [int(c) for c in cpus.split(",")] if cpus else range(os.cpu_count() or 1))
with sync_playwright() as p:
    browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
    if idle:
        idle_autogroups()
    pages = [browser.new_context().new_page() for _ in range(n)]
    for page in pages:
        page.goto(url)
        page.wait_for_selector(".uplot", state="attached", timeout=240_000)
    if idle:
        idle_autogroups()
    print("ready", flush=True)
    sys.stdin.read()
    # ended at once: a browser held to idle CPU may take minutes to close on a busy machine
    for pid in descendants():
        try:
            os.kill(pid, 9)
        except OSError:
            pass
    os._exit(0)
"""


def run_family(print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """The live loop's rate alone, serving three browsers, and with them rendering beside it."""
    rates: tuple[float, float, float] | None | str
    try:
        rates = bench_loop_with_browsers()
    except Exception as exc:  # noqa: BLE001 - a browser that does not come up is a skipped figure, not a crash
        rates = f"{type(exc).__name__}: {str(exc).splitlines()[0]}"
    if isinstance(rates, str):
        print_fn(f"live loop with browsers: failed to open the pages ({rates})")
        return {}
    if rates is None:
        print_fn("live loop with browsers: skipped (needs Debian's chromium and playwright: make test installs both)")
        return {}
    alone, served, watched = rates
    print_fn(
        f"live loop at 30 Hz (vision in the loop): {alone:.2f} Hz with no browser; serving 3 browsers"
        f" {served:.2f} Hz ({(served / alone - 1) * 100:+.1f} %, target within 5 %); 3 browsers rendering"
        f" software WebGL on this same machine {watched:.2f} Hz ({(watched / alone - 1) * 100:+.1f} %)"
    )
    return {"loop_hz_no_browser": alone, "loop_hz_3_browsers_served": served, "loop_hz_3_browsers_same_machine": watched}


FAMILY = Family('browsers', run_family, "the live loop's rate with three browsers watching",
                default=False, order=30)
