"""Long recordings: report and replay on one, and random damage to it (`omniformation bench --long-recording`)."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def write_long_recording(path: Any, minutes: float) -> tuple[int, float]:
    """A recording as `run` makes one: the live loop with vision in the loop on the synthetic
    camera (3 followers, the leader on eq. 39's turns, then straight), frames at 10 Hz, stepped as fast as
    the machine goes (lossless writer). (ticks, seconds it took)."""
    import time as _time

    from app.live.config import DEFAULT_CONFIG, load_service_config
    from app.live.loop import ServiceLoop
    from app.backends.world import Backends
    from app.params import MAX_FOLLOWERS, ParamsStore, default_slots
    from app.recording.writer import Recorder

    config = load_service_config(DEFAULT_CONFIG, MAX_FOLLOWERS)
    from app.params import Params

    store = ParamsStore(Params(n_followers=3, slots=default_slots(3), leader_mode="eq39"))
    loop = ServiceLoop(store, Backends(seed=3, dynamics=config.dynamics, camera=config.camera()), rate_hz=30.0)
    rec = Recorder(path, {"scenario": "long", "command": "omniformation bench --long-recording"}, store.get(),
                   frame_rate_hz=10.0, lossless=True)
    loop.subscribe(rec.on_tick)
    n = int(minutes * 60 * 30)
    start = _time.monotonic()
    try:
        for _ in range(n):
            loop.tick()
    finally:
        loop.halt_followers()
        rec.close()
    return n, _time.monotonic() - start


def bench_long_recording(minutes: float, print_fn: Callable[[str], None] = print) -> dict[str, float]:
    """report and replay on a long recording: peak memory and time of `report` (a fresh process),
    and the time replay takes to open it, to show the first frame and to seek."""
    import resource
    import subprocess
    import sys
    import tempfile
    import time as _time
    from pathlib import Path

    folder = Path(tempfile.mkdtemp(prefix="omniformation-long-"))
    path = folder / "long.mcap"
    print_fn(f"writing a {minutes:g}-minute live-like recording ...")
    ticks, took = write_long_recording(path, minutes)
    size = path.stat().st_size
    print_fn(f"  {ticks} ticks, {size / 1e6:.0f} MB in {took:.0f} s")
    damage_table(path, minutes, print_fn)
    loss_cases(path, print_fn)
    t0 = _time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "app.cli", "report", str(path), "--out", str(folder / "report")],
                          capture_output=True, text=True)
    report_s = _time.monotonic() - t0
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e3
    if proc.returncode != 0:
        print_fn(f"report failed: {proc.stderr.strip()[-300:]}")
    print_fn(f"report: {report_s:.1f} s, peak RSS {peak_mb:.0f} MB (targets for a 1-hour recording: <= 90 s,"
             " <= 400 MB)")
    # replay in a fresh process too: its own peak memory, not this one's (which wrote the file)
    proc = subprocess.run([sys.executable, "-c", "import sys; from app.cli.bench.recordings import replay_probe;"
                           " replay_probe(sys.argv[1])", str(path)], capture_output=True, text=True)
    if proc.returncode != 0:
        print_fn(f"replay failed: {proc.stderr.strip()[-300:]}")
        return {"report_s": report_s, "report_peak_mb": peak_mb}
    probe = json.loads(proc.stdout.strip().splitlines()[-1])
    print_fn(f"replay: open and first frame {probe['first_s']:.2f} s (target <= 5 s; frame {probe['frame']});"
             f" seek anywhere median {probe['seek_median_s']:.2f} s, max {probe['seek_max_s']:.2f} s (target <= 1 s);"
             f" peak RSS {probe['peak_mb']:.0f} MB after {probe['seeks']} seeks")
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    return {"report_s": report_s, "report_peak_mb": peak_mb, "replay_first_s": probe["first_s"],
            "replay_seek_max_s": probe["seek_max_s"], "replay_peak_mb": probe["peak_mb"]}


def damage_table(path: Any, minutes: float, print_fn: Callable[[str], None] = print,
                 flip_counts: tuple[int, ...] = (10, 100), seed: int = 7) -> list[dict[str, float]]:
    """Random bytes of a long recording flipped (10, then 100): per file, the chunks damaged, the
    ticks and frames lost (said by the reader, and checked against the whole file), whether the
    loss stays within one second per damaged chunk, and whether replay opens it. Also the
    writer's chunk count per hour (each costs it 48 bytes of memory until the file closes)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from app.recording.reader import McapScan, read_recording

    whole = read_recording(Path(path))
    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        f.read(8)
        scan = McapScan(f, size)
        scan.run()
    chunks = len(scan.places)
    print_fn(f"writer: {chunks} chunks in {minutes:g} min ({chunks * 60 / minutes:.0f} an hour: its chunk index"
             f" holds {chunks * 60 / minutes * 48 / 1e3:.0f} KB an hour until the file closes)")
    all_ticks = set(whole.tick_numbers.tolist())
    dt = whole.tick_dt()
    rows = []
    rng = np.random.default_rng(seed)
    for count in flip_counts:
        bad = Path(path).with_name(f"flipped-{count}.mcap")
        shutil.copyfile(path, bad)
        with open(bad, "r+b") as f:
            for at in rng.integers(8, size, count):
                f.seek(int(at))
                byte = f.read(1)
                f.seek(int(at))
                f.write(bytes([byte[0] ^ int(rng.integers(1, 256))]))
        rec = read_recording(bad)
        lost = len(all_ticks - set(rec.tick_numbers.tolist()))
        damaged = sum(1 for d in rec.damage if not d.why.startswith("cut off"))
        frames_lost = len(whole.frame_t) - len(rec.frame_t)
        probe = subprocess.run([sys.executable, "-c", "import sys; from app.cli.bench.recordings import replay_probe;"
                                " replay_probe(sys.argv[1], 5)", str(bad)], capture_output=True, text=True)
        row = {"flips": count, "damaged_chunks": damaged, "lost_ticks": lost, "lost_s": lost * dt,
               "said_ticks": rec.lost_ticks, "frames_lost": frames_lost, "replay_opens": probe.returncode == 0}
        rows.append(row)
        print_fn(f"damage: {count} random flips: {damaged} damaged chunks; {lost} ticks lost ({lost * dt:.2f} s; the"
                 f" reader says {rec.lost_ticks}, {rec.lost_s:.2f} s), {frames_lost} of {len(whole.frame_t)} frames"
                 f" lost; within 1 s per damaged chunk: {'yes' if lost * dt <= damaged * 1.0 + 1e-6 else 'NO'};"
                 f" replay opens it: {'yes' if probe.returncode == 0 else 'NO: ' + probe.stderr.strip()[-200:]}")
        rec.close()
        bad.unlink()
    whole.close()
    return rows


def loss_cases(path: Any, print_fn: Callable[[str], None] = print, trials: int = 40, seed: int = 11) -> list[dict[str, Any]]:
    """The loss said against the true loss (ticks of the whole file not read) where a damaged
    record could end the reading or a damaged summary give the count: the first or the second
    chunk's opcode turned into the footer's (0x02); one chunk in ten with its opcode turned into another; and
    ``trials`` times 100 random flips, one to five of them in the summary. Each damage is made in
    place and undone after the file is read. A row says how often the loss said fell short, and
    how often it did without the reader saying that a loss after the last tick read cannot be
    counted."""
    from pathlib import Path

    from app.recording.reader import RecordingError, McapScan, read_recording

    path = Path(path)
    whole = read_recording(path)
    all_ticks, dt = set(whole.tick_numbers.tolist()), whole.tick_dt()
    whole.close()
    size = path.stat().st_size
    with open(path, "rb") as f:
        f.read(8)
        scan = McapScan(f, size)
        scan.run()
        f.seek(size - 28)
        summary_at = int.from_bytes(f.read(8), "little")
    rng = np.random.default_rng(seed)

    def xor(flips: dict[int, int]) -> None:
        """Each byte at an offset xored with its mask: once damages the file, twice undoes it."""
        with open(path, "r+b") as f:
            for at, mask in flips.items():
                f.seek(at)
                byte = f.read(1)[0]
                f.seek(at)
                f.write(bytes([byte ^ mask]))

    def read_damaged(flips: dict[int, int]) -> tuple[int, int, str]:
        """(ticks lost truly, ticks lost said, the note) with the file damaged by ``flips``."""
        xor(flips)
        try:
            rec = read_recording(path)
            true, said, note = len(all_ticks - set(rec.tick_numbers.tolist())), rec.lost_ticks, rec.loss_note()
            rec.close()
        except RecordingError as exc:
            true, said, note = len(all_ticks), 0, str(exc)
        finally:
            xor(flips)
        return true, said, note

    other_ops = [op for op in range(0x12) if op != 0x06]
    cases: list[tuple[str, list[dict[int, int]]]] = [
        ("first chunk's opcode 0x06 -> 0x02", [{scan.places[0][0]: 0x06 ^ 0x02}]),
        ("second chunk's opcode 0x06 -> 0x02", [{scan.places[1][0]: 0x06 ^ 0x02}]),
        ("one chunk in ten: opcode 0x06 -> another", [{pos: 0x06 ^ int(rng.choice(other_ops))
                                                        for pos, _ in scan.places[::10]}]),
        (f"100 random flips, 1-5 in the summary ({trials} trials)", [
            {int(at): int(rng.integers(1, 256)) for at in np.concatenate(
                [rng.integers(8, size, 100 - k), rng.integers(summary_at, size, k)])}
            for k in rng.integers(1, 6, trials)]),
    ]
    rows: list[dict[str, Any]] = []
    for name, damages in cases:
        short = silent = 0
        said_s = true_s = 0.0
        for flips in damages:
            true, said, note = read_damaged(flips)
            said_s, true_s = said_s + said * dt, true_s + true * dt
            if said < true:
                short += 1
                silent += "cannot be counted" not in note  # the file is whole in length: never "cut off"
        n = len(damages)
        rows.append({"case": name, "trials": n, "said_s": said_s / n, "true_s": true_s / n, "short": short,
                     "short_silently": silent})
        print_fn(f"loss: {name}: said {said_s / n:.2f} s, true {true_s / n:.2f} s (mean); said < true in {short} of {n}"
                 f" ({silent} without saying that a loss after the last tick read cannot be counted)")
    return rows


def replay_probe(path: str, seeks: int = 100) -> None:
    """Open a recording for replay, show its first tick, then seek to `seeks` random places (the
    timeline's seek: the plots' last 60 s and the state there); print the times and this
    process's peak RSS as one JSON line (bench --long-recording runs it in a fresh process)."""
    import resource
    from pathlib import Path

    from app.recording.reader import read_recording
    from app.services.replay import ReplayService

    t0 = time.monotonic()
    rec = read_recording(Path(path))
    svc = ReplayService(rec, host="127.0.0.1", port=0)
    first = svc.state_at(0)  # the first tick with its frame, as published when the page opens
    first_s = time.monotonic() - t0
    times = []
    rng = np.random.default_rng(0)
    for k in rng.integers(0, len(rec.ticks), seeks):
        t1 = time.monotonic()
        svc.seek(int(k))
        times.append(time.monotonic() - t1)
    svc.close()
    rec.close()
    print(json.dumps({"first_s": first_s, "frame": first.frame is not None, "seek_median_s": float(np.median(times)),
                      "seek_max_s": max(times), "seeks": seeks,
                      "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3}))

