"""MCAP's own checks (tests/mcap_doctor.py, what `mcap doctor` checks) on every kind of file we
write: the doctor itself is shown to find what it must; `run`, `simulate --record` and `rerun`
recordings are checked where tests/app/recording/test_recording.py makes them, the fleet's here."""

from __future__ import annotations

import shutil
import time

import pytest

from tests.helpers import ROOT
from tests.mcap_doctor import doctor

def test_a_channel_that_never_carried_a_message_is_not_in_the_summary(tmp_path):
    """A writer told of two channels, one of which never carries a message (as /scan and
    /omniformation/trials in a session without obstacles or step tests): the summary names only
    the used one, so every schema and channel in it is also in the data section."""
    from app.recording.mcap_out import SessionWriter

    path = tmp_path / "unused.mcap"
    with open(path, "xb") as f:
        w = SessionWriter(f, 1 << 20, 1.0)
        w.start(library="test")
        used = w.register_channel("/a", "json", w.register_schema("A", "jsonschema", b"{}"))
        w.register_channel("/b", "json", w.register_schema("B", "jsonschema", b"{}"))  # never carries a message
        w.add_message(used, log_time=1, data=b"{}", publish_time=1)
        w.finish()
    assert doctor(path) == []


def test_the_doctor_finds_a_bad_chunk_crc_and_a_footer_among_the_chunks(tmp_path):
    """A session's file passes; a byte flipped inside its first chunk fails the chunk's checks;
    its opcode turned into the footer's fails the record's."""
    from app.params import Params
    from app.recording.reader import McapScan
    from app.recording.writer import Recorder

    good = tmp_path / "good.mcap"
    Recorder(good, {"k": "v"}, Params()).close()
    assert doctor(good) == []
    data = good.read_bytes()
    with open(good, "rb") as f:
        f.read(8)
        scan = McapScan(f, len(data))
        scan.run()
    chunk_at, length = scan.places[0]
    crc = bytearray(data)
    crc[chunk_at + 9 + length - 3] ^= 0x55  # inside the compressed records
    (tmp_path / "crc.mcap").write_bytes(bytes(crc))
    found = doctor(tmp_path / "crc.mcap")
    assert any(f"chunk at {chunk_at}" in e for e in found), found
    footer = bytearray(data)
    footer[chunk_at] = 0x02
    (tmp_path / "footer.mcap").write_bytes(bytes(footer))
    found = doctor(tmp_path / "footer.mcap")
    assert any(f"at {chunk_at} (opcode 0x02)" in e for e in found), found


@pytest.mark.parametrize("sample", sorted((ROOT / "recordings" / "samples").glob("*.mcap")), ids=lambda p: p.stem)
def test_the_samples_pass_mcaps_checks(sample):
    """The samples (`make samples`: simulate --vision --record) pass as every fresh file must."""
    assert doctor(sample) == []


def test_the_fleet_recorders_file_passes_mcaps_checks(tmp_path):
    """The fleet's recorder (app/recording/fleet.py) on its own writer thread: a leader's state
    and events, the arena's truth, over more than one chunk's second."""
    from app.recording.fleet import FleetRecorder

    path = tmp_path / "fleet.mcap"
    rec = FleetRecorder(path)
    for k in range(60):
        rec.write("L1/state", {"k": k, "p": [0.1 * k, 0.0]})
        rec.write("arena/truth", {"k": k})
        if k % 20 == 0:
            rec.write("L1/events", {"kind": "phase", "k": k})
        time.sleep(0.025)
    rec.close()
    assert not rec.failure and rec.written == 60 + 60 + 3
    assert doctor(path) == []
    copy = tmp_path / "copy.mcap"
    shutil.copyfile(path, copy)
    data = bytearray(copy.read_bytes())
    data[len(data) // 3] ^= 0xFF
    copy.write_bytes(bytes(data))
    assert doctor(copy) != []  # the same check fails on a damaged copy
