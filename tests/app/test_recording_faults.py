"""Recordings that survive the disk: a full disk (a real tmpfs) stops the recording cleanly and
says so, the file stays readable, closing never hangs, the loop carries on; a free-space floor;
a retention budget that deletes the oldest sessions and never the samples."""

from __future__ import annotations

import contextlib
import os
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
from app.live.params import ParamsStore
from app.recording.reader import read_recording
from app.recording.writer import Recorder, RecordingRefused, apply_retention
from tests.helpers import ROOT, main_cli, wait_for


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
    loop = ServiceLoop(store, rate_hz=30.0, seed=seed)
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
        assert len(read_recording(disk / "s.mcap").ticks) > 0


def test_retention_deletes_only_the_services_own_sessions_oldest_first_never_the_samples(tmp_path):
    """Sessions are known by what the writer put in them (its header and metadata), not by name:
    another program's MCAP files, a file named like a session and the samples are never deleted."""
    from mcap.writer import Writer

    from app.live.params import Params

    folder = tmp_path / "recordings"
    (folder / "samples").mkdir(parents=True)
    sample = folder / "samples" / "kept.mcap"
    shutil.copyfile(ROOT / "recordings" / "samples" / "experiment2-vision.mcap", sample)
    names = []
    for k in range(5):
        p = folder / f"2026010{k}T000000Z_sim.mcap"
        Recorder(p, {"k": str(k)}, Params()).close()
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
    for p in (foreign, lookalike):
        os.utime(p, (1_000, 1_000))
    deleted = apply_retention(folder, int(2.5 * size), keep=(names[0],))  # counts the sessions only
    assert deleted == names[1:4]  # oldest first, the one being written is kept
    assert sorted(p for p in folder.glob("*.mcap")) == sorted([names[0], names[4], foreign, lookalike])
    assert sample.exists()
    assert apply_retention(folder, 0, keep=(names[0],)) == [names[4]]
    assert foreign.exists() and lookalike.exists() and sample.exists()


SAMPLE = ROOT / "recordings" / "samples" / "experiment2-vision.mcap"


def _scan(path: Path):
    from app.recording.reader import _Scan

    with open(path, "rb") as f:
        f.read(8)
        scan = _Scan(f, path.stat().st_size)
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


@pytest.mark.parametrize("at", [0.02, 0.10, 0.30, 0.55, 0.93])  # the first chunk too: its channels are known elsewhere
def test_a_flipped_byte_skips_one_chunk_and_says_exactly_what_was_lost(tmp_path, at):
    whole = read_recording(SAMPLE)
    bad = tmp_path / "flipped.mcap"
    _flip(SAMPLE, bad, at)
    rec = read_recording(bad)
    assert rec.complete and len(rec.damage) == 1 and rec.bytes_read >= rec.bytes_total - _one_chunk_of_bytes(SAMPLE)
    lost = len(whole.ticks) - len(rec.ticks)
    assert 0 < lost <= _one_chunk_of_ticks(SAMPLE) < 0.5 * len(whole.ticks)  # one chunk's worth, not the rest
    gaps = rec.gaps()
    assert sum(g.ticks for g in gaps) == lost  # every missing tick is accounted for
    assert set(rec.tick_numbers) < set(whole.tick_numbers)
    assert len(rec.gaps()) == 1 and (rec.gaps()[0].after_tick == -1) == (at < 0.15)  # the first chunk: a lead gap
    note = rec.loss_note()
    assert f"{lost} ticks (" in note and "1 damaged stretch of the file" in note
    assert rec.ticks[-1] == whole.ticks[-1]  # read on past the damage to the end


def test_damage_to_a_chunk_length_field_is_stepped_over(tmp_path):
    from app.recording.reader import _Scan

    with open(SAMPLE, "rb") as f:
        size = SAMPLE.stat().st_size
        f.read(8)
        scan = _Scan(f, size)
        scan.run()
    pos, _ = scan.places[len(scan.places) // 2]
    data = bytearray(SAMPLE.read_bytes())
    data[pos + 5] ^= 0x40  # the chunk record's length: now it claims terabytes
    bad = tmp_path / "length.mcap"
    bad.write_bytes(bytes(data))
    rec = read_recording(bad)
    whole = read_recording(SAMPLE)
    assert len(rec.damage) == 1 and 0 < len(whole.ticks) - len(rec.ticks) <= _one_chunk_of_ticks(SAMPLE)
    assert sum(g.ticks for g in rec.gaps()) == len(whole.ticks) - len(rec.ticks)


def test_a_cut_off_file_says_how_many_bytes_were_not_read(tmp_path):
    data = SAMPLE.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    rec = read_recording(cut)
    assert not rec.complete
    tail = rec.bytes_total - rec.damage[-1].start_byte
    assert 0 < tail <= _one_chunk_of_bytes(SAMPLE)
    assert f"the last {tail} bytes (an unfinished chunk" in rec.loss_note()


def test_report_on_a_damaged_file_says_what_was_lost_and_writes_the_figures(tmp_path):
    from tests.helpers import main_cli

    bad = tmp_path / "flipped.mcap"
    _flip(SAMPLE, bad, 0.30)
    res = main_cli("report", str(bad), "--out", str(tmp_path / "rep"))
    assert res.returncode == 0, res.stderr
    assert "ticks (" in res.stderr and "damaged stretch" in res.stderr
    summary = (tmp_path / "rep" / "summary.md").read_text()
    assert "missing" in summary and "damaged" in summary


def test_a_cut_off_session_with_its_first_chunk_damaged_is_read_from_the_metadata_channel_table(tmp_path):
    """No summary (killed) and the chunk that announced the channels damaged: the channel table
    the writer put in its metadata (twice, before the first chunk) names them; each copy of the
    metadata alone is enough."""
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
