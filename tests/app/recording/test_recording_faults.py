"""Recordings that survive the disk: a full disk (a real tmpfs) stops the recording cleanly and
says so, the file stays readable, closing never hangs, the loop carries on; a free-space floor;
a retention budget that deletes the oldest sessions and never the samples."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from app.live.loop import ServiceLoop
from app.backends.world import Backends
from app.params import ParamsStore
from app.recording.reader import read_recording
from app.recording.writer import Recorder, RecordingRefused, apply_retention
from tests.helpers import ROOT, main_cli, serve_then_signal, wait_for


@contextlib.contextmanager
def tmpfs(path: Path, size: str) -> Iterator[Path]:
    """A real small disk: tmpfs mounted at ``path`` (root only; skipped where mount is refused)."""
    path.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({res.stderr.strip() or 'not root'}): the full-disk tests need one")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def noisy_ticks(n_ticks: int, seed: int = 0):
    """A simulated team's ticks, each with a camera frame of noise (JPEG cannot shrink it)."""
    store = ParamsStore()
    store.update("test", leader_mode="straight")
    loop = ServiceLoop(store, Backends(seed=seed), rate_hz=30.0)
    rng = np.random.default_rng(seed)
    for _ in range(n_ticks):
        s = loop.tick()
        frame = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
        yield s.__class__(**{**s.__dict__, "frame": frame})


def test_a_full_disk_stops_the_recording_cleanly_and_the_file_stays_readable(tmp_path):
    with tmpfs(tmp_path / "disk", "8m") as disk:
        stops: list[str] = []
        path = disk / "session.mcap"
        rec = Recorder(path, {"scenario": "test"}, ParamsStore().get(), frame_rate_hz=30.0, on_stopped=stops.append)
        fed = 0
        for s in noisy_ticks(900):
            rec.on_tick(s)  # never raises, never blocks: the loop carries on
            fed += 1
            if stops:
                break
            time.sleep(0.002)
        wait_for(lambda: bool(stops), 30, "the recording to notice the full disk")
        assert "No space left on device" in rec.failure and stops == [rec.failure] and not rec.recording
        rec.on_tick(next(noisy_ticks(1)))  # ignored after the stop
        t0 = time.monotonic()
        rec.close()
        assert time.monotonic() - t0 < 15  # closing does not hang on the full disk
        back = read_recording(path)
        assert len(back.ticks) > 10 and back.frames, "what was written before the disk filled is readable"
        assert back.ticks[-1]["tick"] < fed


def test_a_recording_refuses_to_start_below_the_free_space_floor_and_stops_when_it_is_crossed(tmp_path):
    with tmpfs(tmp_path / "disk", "8m") as disk:
        with pytest.raises(RecordingRefused, match="below the floor of 100 MB"):
            Recorder(disk / "a.mcap", {}, ParamsStore().get(), free_floor_bytes=100 * 10**6)
        assert not (disk / "a.mcap").exists()
        stops: list[str] = []
        rec = Recorder(disk / "b.mcap", {}, ParamsStore().get(), frame_rate_hz=30.0,
                       free_floor_bytes=5 * 2**20, on_stopped=stops.append)
        for s in noisy_ticks(900, seed=1):
            rec.on_tick(s)
            if stops:
                break
            time.sleep(0.002)
        wait_for(lambda: bool(stops), 30, "the floor to be crossed")
        assert "the disk is nearly full" in rec.failure and "below the floor of 5 MB" in rec.failure
        rec.close()
        assert len(read_recording(disk / "b.mcap").ticks) > 10
        assert os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize > 2 * 2**20  # stopped with room to spare


def test_run_on_a_full_disk_keeps_serving_says_so_and_exits_0_on_sigterm(tmp_path):
    with tmpfs(tmp_path / "disk", "2m") as disk:
        refused = subprocess.run([sys.executable, "-m", "app.cli", "run", "--port", "0", "--record", str(disk / "r.mcap")],
                                 cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert refused.returncode == 2 and "below the floor of 500 MB" in refused.stderr  # default.toml's floor
        assert "Traceback" not in refused.stderr and not (disk / "r.mcap").exists()
        # a recordings folder not made yet is measured on the disk that would hold it: refused the same
        # way, before anything starts, and the folder is not made
        folder = disk / "not" / "yet"
        refused = subprocess.run([sys.executable, "-m", "app.cli", "run", "--port", "0", "--recordings", str(folder)],
                                 cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert refused.returncode == 2 and "below the floor of 500 MB" in refused.stderr, refused.stderr
        assert len(refused.stderr.strip().splitlines()) == 1 and not (disk / "not").exists()
        config = tmp_path / "floorless.toml"
        camera = ROOT / "static_config" / "camera"
        config.write_text(f'[camera]\nrig = "{camera / "synthetic.toml"}"\ncalibration = "{camera / "synthetic_calibrated.toml"}"\n'
                          "[recording]\nfree_space_floor_mb = 0\n")
        proc = subprocess.Popen([sys.executable, "-m", "app.cli", "run", "--port", "0", "--record",
                                 str(disk / "s.mcap"), "--frames-hz", "30", "--config", str(config)], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            lines: list[str] = []
            deadline = time.monotonic() + 120
            while time.monotonic() < deadline:
                line = proc.stderr.readline() if proc.stderr else ""
                if not line and proc.poll() is not None:
                    break
                lines.append(line)
                if "recording stopped" in line:
                    break
            assert any("recording stopped: writing failed: No space left on device" in ln for ln in lines), lines
            assert proc.poll() is None  # the service and the robots carry on
            time.sleep(1.0)
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
        assert proc.returncode == 0, err
        assert "Traceback" not in err and "all followers commanded to zero" in out
        rec = read_recording(disk / "s.mcap")
        assert len(rec.ticks) > 0
        said = re.search(r"holds (\d+) of the (\d+) ticks it was given; (\d+) were not written \(writing failed", out)
        assert said, out
        held, given, missing = (int(x) for x in said.groups())
        assert held == len(rec.ticks) and held + missing == given  # the closing line's counts are the file's
        assert rec.tick_numbers[0] == 0 and rec.lost_ticks == 0  # what the file holds, it holds whole


SERVICE = {"retention": "service"}  # what the live service marks its sessions with (docs: README, retention)


def test_retention_deletes_only_the_services_own_sessions_oldest_first_never_the_samples(tmp_path):
    """Sessions are known by what the writer put in them (its header and metadata), not by name:
    another program's MCAP files, a file named like a session, the samples and what another
    command recorded (simulate --record) are never deleted; a session being written (locked)
    counts but is never deleted."""
    from mcap.writer import Writer

    from app.params import Params

    folder = tmp_path / "recordings"
    (folder / "samples").mkdir(parents=True)
    sample = folder / "samples" / "kept.mcap"
    shutil.copyfile(ROOT / "recordings" / "samples" / "experiment2-vision.mcap", sample)
    names = []
    for k in range(5):
        p = folder / f"2026010{k}T000000Z_sim.mcap"
        Recorder(p, {"k": str(k), **SERVICE}, Params()).close()
        os.utime(p, (1_000_000 + k, 1_000_000 + k))
        names.append(p)
    size = names[0].stat().st_size
    foreign = folder / "20250101T000000Z_other.mcap"  # another program's MCAP file, older than every session
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start(profile="", library="someone else")
        w.add_metadata("notes", {"a": "b"})
        w.finish()
    lookalike = folder / "20250101T000001Z_sim.mcap"
    lookalike.write_bytes(b"x" * (10 * size))
    simulated = folder / "20250101T000002Z_simulated.mcap"
    assert main_cli("simulate", "experiment1", "--duration", "0.5", "--record", str(simulated)).returncode == 0
    for p in (foreign, lookalike, simulated):
        os.utime(p, (1_000, 1_000))
    sim_size = simulated.stat().st_size
    deleted = apply_retention(folder, int(2.5 * size) + sim_size, keep=(names[0],))  # counts the sessions only
    assert deleted == names[1:4]  # oldest first, the one kept is kept, the simulated one is not the service's
    assert sorted(p for p in folder.glob("*.mcap")) == sorted([names[0], names[4], foreign, lookalike, simulated])
    assert sample.exists()
    live = folder / "20260109T000000Z_live.mcap"
    writing = Recorder(live, dict(SERVICE), Params())  # being written: locked
    try:
        os.utime(live, (1_000, 1_000))  # the oldest session of all
        assert apply_retention(folder, 0, keep=(names[0],)) == [names[4]]
        assert live.exists()
    finally:
        writing.close()
    assert apply_retention(folder, 0) == [names[0], live]  # finished: now it may go
    assert foreign.exists() and lookalike.exists() and sample.exists() and simulated.exists()


def test_two_services_on_one_folder_never_delete_each_others_live_session(tmp_path):
    """Two `run` services record into one folder with a 10 MB budget. The folder holds an older
    recording of `simulate --record`; while the first service records, an 11 MB session of a
    service, newer than anything, is added: the first's live file is the oldest session. When the second starts, its retention
    deletes the 11 MB session only: the live file is locked, the simulated one is not the
    service's. The first's closing line counts the ticks its file holds."""
    from app.params import Params

    folder = tmp_path / "recordings"
    folder.mkdir()
    simulated = folder / "simulated.mcap"
    assert main_cli("simulate", "experiment1", "--duration", "0.5", "--record", str(simulated)).returncode == 0
    os.utime(simulated, (1_000, 1_000))
    big = folder / "big.mcap"
    camera = ROOT / "static_config" / "camera"
    config = tmp_path / "small-budget.toml"
    config.write_text(f'[camera]\nrig = "{camera / "synthetic.toml"}"\ncalibration = "{camera / "synthetic_calibrated.toml"}"\n'
                      "[recording]\nmax_total_gb = 0.01\nfree_space_floor_mb = 0\n")
    first, second = folder / "first.mcap", folder / "second.mcap"
    runs = {}

    def start_the_second() -> bool:
        rec = Recorder(big, dict(SERVICE), Params(), frame_rate_hz=30.0, lossless=True)  # made while the first runs
        for s in noisy_ticks(300, seed=2):
            rec.on_tick(s)
            if rec.ticks % 30 == 0 and big.stat().st_size > 11 * 10**6:
                break
        rec.close()
        assert big.stat().st_size > 10**7
        future = time.time() + 86_400
        os.utime(big, (future, future))
        runs["second"] = serve_then_signal("--port", "0", "--feedback", "truth", "--config", str(config),
                                           "--record", str(second), hold_s=1.0)
        return True

    runs["first"] = serve_then_signal("--port", "0", "--feedback", "truth", "--config", str(config),
                                      "--record", str(first),
                                      until=lambda: first.exists() and first.stat().st_size > 5_000 and start_the_second())
    a, b = runs["first"], runs["second"]
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    assert "deleted the oldest" in b.stderr and "big.mcap" in b.stderr and "first.mcap" not in b.stderr
    assert not big.exists() and simulated.exists() and first.exists() and second.exists()
    said = re.search(r"recording finished: first\.mcap \((\d+) ticks\)", a.stdout)
    assert said, a.stdout
    back = read_recording(first)
    assert back.complete and len(back.ticks) == int(said.group(1)) and back.lost_ticks == 0
    assert len(read_recording(second).ticks) > 0


SAMPLE = ROOT / "recordings" / "samples" / "experiment2-vision.mcap"


def _scan(path: Path):
    from app.recording.reader import McapScan

    with open(path, "rb") as f:
        f.read(8)
        scan = McapScan(f, path.stat().st_size)
        scan.run()
    return scan


def _one_chunk_of_ticks(path: Path) -> int:
    """The most ticks any one chunk of the file holds: what one damaged chunk may cost."""
    from app.recording.schema import TICK_TOPIC

    chunks = list(_scan(path).index[TICK_TOPIC][1])
    return max(chunks.count(c) for c in set(chunks))


def _one_chunk_of_bytes(path: Path) -> int:
    """The most bytes from one chunk's start to the next one's (the chunk and its message
    indexes): what one damaged chunk may cost."""
    starts = [pos for pos, _ in _scan(path).places]
    return max(b - a for a, b in zip(starts, starts[1:]))


def _flip(src: Path, dst: Path, at: float, width: int = 1) -> int:
    data = bytearray(src.read_bytes())
    k = int(len(data) * at)
    for i in range(k, k + width):
        data[i] ^= 0xFF
    dst.write_bytes(bytes(data))
    return k


SAMPLE_FILES = sorted((ROOT / "recordings" / "samples").glob("*.mcap"))


def _true_loss(whole, rec) -> int:
    return len(set(whole.tick_numbers.tolist()) - set(rec.tick_numbers.tolist()))


@pytest.mark.parametrize("sample", SAMPLE_FILES, ids=lambda p: p.stem)
def test_one_flipped_byte_anywhere_costs_at_most_a_second_and_a_half_and_the_loss_is_said_exactly(tmp_path, sample):
    """The damage table: one byte flipped at 2 %, 10 %, 50 %, 90 % of each sample. Every file
    reads, the loss is at most 1.5 s of ticks, and what the reader and the report say was lost is
    what was lost (the ticks the whole file has and the damaged one has not)."""
    from app.recording.report import summarise

    whole = read_recording(sample)
    dt = whole.tick_dt()
    for at in (0.02, 0.10, 0.50, 0.90):
        bad = tmp_path / f"flip-{at}.mcap"
        _flip(sample, bad, at)
        rec = read_recording(bad)
        lost = _true_loss(whole, rec)
        print(f"\n{sample.name} flipped at {at:.0%}: {lost} ticks lost ({lost * dt:.2f} s), {len(rec.frames)} of"
              f" {len(whole.frames)} frames read")
        assert rec.complete and rec.ticks_written == len(whole.ticks)
        assert lost * dt <= 1.5
        assert rec.lost_ticks == lost and len(rec.ticks) + rec.lost_ticks == rec.ticks_written
        assert rec.ticks[-1] == whole.ticks[-1]  # read on past the damage to the end
        if lost:
            assert f"{lost} ticks (" in rec.loss_note()
        if at == 0.10:
            summary = summarise(rec)
            assert summary["lost_ticks"] == lost and summary["ticks_read"] + lost == summary["ticks_written"]


@pytest.mark.parametrize("sample", SAMPLE_FILES, ids=lambda p: p.stem)
def test_a_file_cut_at_60_percent_keeps_all_but_its_last_second_and_a_half(tmp_path, sample):
    """Cut at 60 % of its bytes (a killed writer, a pulled disk): every tick in a chunk that ended
    before the cut is read, and the ticks lost before the cut's moment are at most 1.5 s."""
    whole = read_recording(sample)
    data = sample.read_bytes()
    at = int(len(data) * 0.6)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:at])
    rec = read_recording(cut)
    assert not rec.complete
    scan = _scan(sample)
    chunk_of = np.frombuffer(scan.index["/omniformation/tick"][1], dtype=np.int64)
    started = np.array([pos < at for pos, _ in scan.places])
    t_by_then = float(whole.t[started[chunk_of]].max())  # the newest tick the session had sent to the file by then
    print(f"\n{sample.name} cut at 60 %: read up to t = {rec.t[-1]:.2f} s of {t_by_then:.2f} s")
    assert t_by_then - float(rec.t[-1]) <= 1.5
    assert rec.lost_ticks == 0 and np.array_equal(rec.tick_numbers, whole.tick_numbers[:len(rec.ticks)])
    tail = rec.bytes_total - rec.damage[-1].start_byte
    assert f"the last {tail} bytes (an unfinished chunk" in rec.loss_note()


def test_damage_to_a_chunk_length_field_is_stepped_over(tmp_path):
    from app.recording.reader import McapScan

    with open(SAMPLE, "rb") as f:
        size = SAMPLE.stat().st_size
        f.read(8)
        scan = McapScan(f, size)
        scan.run()
    ticks_in = np.frombuffer(scan.index["/omniformation/tick"][1], dtype=np.int64)
    pos, _ = scan.places[int(ticks_in[len(ticks_in) // 2])]  # a chunk of ticks in the middle
    data = bytearray(SAMPLE.read_bytes())
    data[pos + 5] ^= 0x40  # the chunk record's length: now it claims terabytes
    bad = tmp_path / "length.mcap"
    bad.write_bytes(bytes(data))
    rec = read_recording(bad)
    whole = read_recording(SAMPLE)
    assert len(rec.damage) == 1 and 0 < len(whole.ticks) - len(rec.ticks) <= _one_chunk_of_ticks(SAMPLE) <= 31
    assert rec.lost_ticks == len(whole.ticks) - len(rec.ticks)


def test_report_on_a_damaged_file_says_what_was_lost_and_writes_the_figures(tmp_path):
    from tests.helpers import main_cli

    scan = _scan(SAMPLE)
    ticks_in = np.frombuffer(scan.index["/omniformation/tick"][1], dtype=np.int64)
    pos, length = scan.places[int(ticks_in[len(ticks_in) // 3])]  # a chunk of ticks
    bad = tmp_path / "flipped.mcap"
    _flip(SAMPLE, bad, (pos + length // 2) / SAMPLE.stat().st_size)
    res = main_cli("report", str(bad), "--out", str(tmp_path / "rep"))
    assert res.returncode == 0, res.stderr
    assert "ticks (" in res.stderr and "damaged stretch" in res.stderr
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert "missing" in summary and "damaged" in summary


def test_a_cut_off_session_with_its_first_chunk_damaged_is_read_from_the_metadata_channel_table(tmp_path):
    """No summary (killed) and the first chunk damaged: the rest is read (every chunk names its
    channels, and the metadata has the channel table too), the first ticks are a gap from the
    session's start, and each copy of the metadata alone is enough."""
    from app.recording.schema import TICK_TOPIC

    path = tmp_path / "s.mcap"
    res = main_cli("simulate", "experiment1", "--duration", "70", "--record", str(path))
    assert res.returncode == 0, res.stderr
    whole = read_recording(path)
    scan = _scan(path)
    assert len(scan.places) >= 3
    first, second = scan.places[0], scan.places[1]
    data = bytearray(path.read_bytes())[:second[0] + second[1] + 9]  # cut off after the second chunk
    data[first[0] + first[1] // 2] ^= 0xFF  # the first chunk (schemas, channels, the first ticks) damaged
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(bytes(data))
    rec = read_recording(cut)
    assert not rec.complete and len(rec.ticks) > 0
    lead = rec.gaps()[0]
    assert lead.after_tick == -1 and lead.before_tick == int(rec.tick_numbers[0]) > 0
    assert rec.ticks[0] == whole.ticks[int(rec.tick_numbers[0])]
    assert rec.channels[TICK_TOPIC] == "omniformation.Tick" and rec.metadata.get("scenario")
    metadata_at = data.find(b"omniformation", 20)  # the first copy of the metadata record
    data[metadata_at] ^= 0xFF
    cut.write_bytes(bytes(data))
    again = read_recording(cut)
    assert len(again.ticks) == len(rec.ticks) and again.metadata == rec.metadata  # the second copy


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory) -> Path:
    """A real session with camera frames, 38 chunks or so: ticks, frames, events, params."""
    path = tmp_path_factory.mktemp("small") / "small.mcap"
    res = main_cli("simulate", "experiment1", "--vision", "--duration", "12", "--frames-hz", "5", "--record", str(path))
    assert res.returncode == 0, res.stderr
    return path


def _top_level_records(data: bytes) -> list[tuple[int, int]]:
    """(offset, length) of every record outside the chunks, header to footer."""
    out, pos = [], 8
    while pos + 9 <= len(data) - 8:
        length = int.from_bytes(data[pos + 1:pos + 9], "little")
        out.append((pos, length))
        pos += 9 + length
    return out


def _summary_start(data: bytes) -> int:
    """Where the summary section starts, from the footer (with its data end record before it)."""
    return int.from_bytes(data[-28:-20], "little") - 13


def test_random_damage_never_raises_and_the_reported_loss_is_the_true_loss(small_recording, tmp_path):
    """Hypothesis damages a real recording (flipped bytes anywhere or in a chunk, a record's
    opcode turned into another one, the footer's 0x02 above all, flips in the summary, a zeroed
    stretch, a cut) and reads it: nothing but a one-line RecordingError (only when no tick is
    left) is raised, every tick read is the tick written, and the loss said is the loss: all of
    it whenever the summary or the writer's count after its last chunk is untouched (a damaged
    record never ends the reading), else every tick missing up to the last one read, with the
    note saying that a loss after it cannot be counted or that the file was cut off."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    from app.recording.reader import RecordingError

    whole = read_recording(small_recording)
    data = small_recording.read_bytes()
    by_number = {int(n): k for k, n in enumerate(whole.tick_numbers)}
    bad = tmp_path / "bad.mcap"
    summary_at = _summary_start(data)
    records = _top_level_records(data)
    counts_at, counts_len = next((pos, n) for pos, n in records if data[pos] == 0x0C and b"omniformation.counts"
                                 in data[pos:pos + 9 + n])  # the writer's count after its last chunk

    places = _scan(small_recording).places  # (offset, length) of each chunk: small tick chunks are as likely hit
    inside = st.tuples(st.integers(0, len(places) - 1), st.floats(0, 1, exclude_max=True)).map(
        lambda c: (places[c[0]][0] + int(c[1] * (places[c[0]][1] + 9))) / len(data))
    in_summary = st.floats(0, 1, exclude_max=True).map(lambda u: (summary_at + u * (len(data) - summary_at)) / len(data))
    opcode = st.one_of(st.just(0x02), st.integers(0x00, 0x11), st.just(0xFF))
    damage = st.one_of(
        st.tuples(st.just("flip"), st.lists(st.tuples(st.floats(0, 1, exclude_max=True) | inside, st.integers(1, 255)),
                                            min_size=1, max_size=30)),
        st.tuples(st.just("opcode"), st.lists(st.tuples(st.integers(0, len(records) - 1), opcode), min_size=1,
                                              max_size=4)),
        st.tuples(st.just("summary"), st.lists(st.tuples(in_summary, st.integers(1, 255)), min_size=1, max_size=5),
                  st.lists(st.tuples(inside, st.integers(1, 255)), max_size=5)),
        st.tuples(st.just("zero"), st.tuples(st.floats(0, 1, exclude_max=True), st.integers(1, 200_000))),
        st.tuples(st.just("cut"), st.floats(0, 1, exclude_max=True)),
    )

    @settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    @given(damage)
    def check(d):
        buf = bytearray(data)
        if d[0] == "flip":
            for at, x in d[1]:
                buf[int(at * len(buf))] ^= x
        elif d[0] == "opcode":
            for k, op in d[1]:
                buf[records[k][0]] = op
        elif d[0] == "summary":
            for at, x in d[1] + d[2]:
                buf[min(int(at * len(buf)), len(buf) - 1)] ^= x
        elif d[0] == "zero":
            start = int(d[1][0] * len(buf))
            buf[start:start + d[1][1]] = bytes(len(buf[start:start + d[1][1]]))
        else:
            del buf[int(d[1] * len(buf)):]
        bad.write_bytes(bytes(buf))
        try:
            rec = read_recording(bad)
        except RecordingError as exc:
            assert "\n" not in str(exc)
            return  # nothing readable was left (or it is no longer an MCAP file at all)
        numbers = [int(n) for n in rec.tick_numbers]
        assert set(numbers) <= set(by_number) and numbers == sorted(numbers)
        for k in (0, len(numbers) - 1):  # what is read is what was written
            assert rec.ticks[k] == whole.ticks[by_number[numbers[k]]]
        missing = set(by_number) - set(numbers)
        end_untouched = len(buf) == len(data) and buf[summary_at:] == data[summary_at:]
        counts_untouched = len(buf) >= counts_at + 9 + counts_len and (buf[counts_at:counts_at + 9 + counts_len]
                                                                      == data[counts_at:counts_at + 9 + counts_len])
        if end_untouched:  # the summary and the footer are as written: the whole loss is known and said
            assert rec.complete and rec.ticks_written == len(whole.ticks)
        if end_untouched or counts_untouched:  # either count left whole: the whole loss is known and said
            assert rec.ticks_written == len(whole.ticks), rec.loss_note()
        if rec.ticks_written is not None:
            assert rec.ticks_written == len(whole.ticks)
        else:  # no count to trust: what came after the last tick read is not known to have been written
            assert not end_untouched and not counts_untouched
            missing = {n for n in missing if n < numbers[-1]}
            assert "cannot be counted" in rec.loss_note() or (not rec.complete and "cut off" in rec.loss_note())
        said: set[int] = set()
        for g in rec.gaps():
            said |= set(range(g.after_tick + 1, g.before_tick))
        assert said == missing and rec.lost_ticks == len(missing)  # how many, and which
        rec.close()

    check()


@pytest.mark.parametrize("sample", SAMPLE_FILES, ids=lambda p: p.stem)
def test_a_chunk_opcode_turned_into_the_footers_or_any_other_never_ends_the_reading(tmp_path, sample):
    """The first chunk's opcode (0x06) turned into the footer's (0x02), the data end's, a
    message's, a schema's, the header's, an unknown one: the chunk is lost and nothing else; the
    reader and `report` say exactly that loss, and the file is not called cut off."""
    from app.recording.report import summarise

    whole = read_recording(sample)
    first = _scan(sample).places[0][0]
    data = bytearray(sample.read_bytes())
    assert data[first] == 0x06
    for op in (0x02, 0x0F, 0x05, 0x03, 0x01, 0x0E, 0x00, 0x11):
        data[first] = op
        bad = tmp_path / f"op{op:02x}.mcap"
        bad.write_bytes(bytes(data))
        rec = read_recording(bad)
        lost = _true_loss(whole, rec)
        assert rec.complete and rec.ticks_written == len(whole.ticks) and rec.ticks[-1] == whole.ticks[-1]
        assert rec.lost_ticks == lost <= _one_chunk_of_ticks(sample) and len(rec.ticks) + lost == len(whole.ticks)
        assert len(rec.damage) == 1 and "cut off" not in rec.loss_note()
        if op == 0x02:
            summary = summarise(rec)
            assert summary["lost_ticks"] == lost and summary["lost_s"] == pytest.approx(lost * whole.tick_dt(), abs=1e-3)
        rec.close()


def test_report_on_a_file_whose_first_chunk_says_footer_counts_the_loss_and_exits_0(small_recording, tmp_path):
    """`report` on a fresh recording whose first chunk's opcode reads 0x02: every later tick is
    read, the loss said is the first chunk's, and the note does not call the file cut off."""
    whole = read_recording(small_recording)
    first = _scan(small_recording).places[0][0]
    data = bytearray(small_recording.read_bytes())
    data[first] = 0x02
    bad = tmp_path / "footer.mcap"
    bad.write_bytes(bytes(data))
    res = main_cli("report", str(bad), "--out", str(tmp_path / "rep"))
    assert res.returncode == 0, res.stderr
    import json

    summary = json.loads((tmp_path / "rep" / "summary.json").read_text())
    rec = read_recording(bad)
    lost = _true_loss(whole, rec)
    assert 0 < lost and summary["lost_ticks"] == lost and summary["ticks_read"] + lost == len(whole.ticks)
    assert "cut off" not in res.stderr


def test_the_benchs_damage_table_counts_what_it_flipped_and_replay_opens_the_files(small_recording, tmp_path):
    """bench --long-recording's damage table on a short recording: the reader's count is the
    true count, within a second per damaged chunk, and replay (a fresh process) opens the file;
    its loss cases (opcodes, the summary) say the true loss and leave the file as it was."""
    from app.cli.bench import damage_table, loss_cases

    copy = tmp_path / "long.mcap"
    shutil.copyfile(small_recording, copy)
    lines: list[str] = []
    rows = damage_table(copy, 0.3, lines.append, flip_counts=(10,))
    assert lines[0].startswith("writer: ") and "damage: 10 random flips" in lines[1]
    (row,) = rows
    assert row["said_ticks"] == row["lost_ticks"] and row["replay_opens"]
    assert row["lost_s"] <= row["damaged_chunks"] * 1.0 + 1e-6
    before = copy.read_bytes()
    cases = loss_cases(copy, lines.append, trials=4)  # its cases of damage that used to end the reading or
    assert [c["trials"] for c in cases] == [1, 1, 1, 4]  # take the count from a damaged summary
    assert all(c["short"] == 0 and c["said_s"] == pytest.approx(c["true_s"]) for c in cases), lines
    assert cases[0]["true_s"] > 0 and copy.read_bytes() == before  # each damage undone
