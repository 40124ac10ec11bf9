"""What "bit for bit" compares of a ``daror hil`` run (D143): one sha256 per stream of its output folder.

The streams, each independent of the wall clock, the session id and the output folder:

* ``cyclic``: the process data, in bus order from the first SYNC on: every SYNC (with its robot time
  in microseconds) and every RPDO and TPDO frame (COB-ID 0x181-0x57F: PDOs of the pre-defined
  connection set) with its payload. Start-up SDO, NMT, heartbeats and EMCY are not in it;
* ``arrays:<file>:<name>``: every array of every ``*.raw.npz`` (dtype, shape and bytes);
* ``dataset:<file>``: every ``*.csv`` dataset, byte for byte;
* ``session``: session.json's state, robot time, joints, model numbers, ISB limits and handover;
* ``audit``: the audit log's events in order (event, robot time, source, destination, fault kind, joint),
  without the jobs that keep ``session.json`` current (D213).

``python -m tests.golden_streams OUT_DIR`` prints them as JSON (how tests/data/daror01_golden.json was made).
"""

from __future__ import annotations

import gzip
import hashlib
import json
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["streams"]

#: PDO COB-IDs of the pre-defined connection set: TPDO1 0x181 .. RPDO4 0x57F.
_PDO_IDS = range(0x181, 0x580)
_SYNC = 0x080
#: session.json's fields that say what the session did (not where or when it was written).
_SESSION_FIELDS = ("t_s", "state", "joints", "isb_limits_deg", "handover_nm", "support_level", "faults")
_MODEL_FIELDS = (
    "name",
    "kind",
    "validated",
    "validation_rmse_nm",
    "validation_rmse_per_joint_nm",
    "closed_path_energy_j",
)
_AUDIT_FIELDS = ("event", "t_s", "source", "dest", "kind", "joint", "reaction", "request")
#: Jobs whose "job started" and "job finished" events are left out of the audit stream: ``session.json``
#: written after every transition (D213), which the golden runs' code did not do.
_BOOKKEEPING_JOBS = ("write session.json",)


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def cyclic_stream(log: Path, epoch_s: int) -> tuple[str, int]:
    """The sha256 of the process data of a candump ``-L`` log (gzip), and how many SYNCs it has.

    A log of the bus log writer's own lines (:data:`_CANONICAL`, every line) is read in blocks
    (:func:`_cyclic_stream_canonical`: the same bytes hashed, a third less time); any other is read
    line by line (:func:`_cyclic_stream_lines`).
    """
    found = _cyclic_stream_canonical(log, epoch_s)
    return found if found is not None else _cyclic_stream_lines(log, epoch_s)


#: A candump ``-L`` line as the bus log's writer writes it (:mod:`hal.canopen.traffic_writer`): a decimal
#: stamp, a channel of printable ASCII, three upper-case hex digits of COB-ID, upper-case hex data, the
#: direction. Anchored at a line's start and ending at its newline: a match is one whole line.
_CANONICAL = re.compile(rb"^\((\d+\.\d+)\) [!-~]+ ([0-9A-F]{3})#([0-9A-F]*) [TR]\n", re.MULTILINE)
#: Decompressed bytes read at a time by :func:`_cyclic_stream_canonical`.
_BLOCK_BYTES = 1 << 22


def _cyclic_stream_canonical(log: Path, epoch_s: int) -> tuple[str, int] | None:
    """:func:`_cyclic_stream_lines`'s answer for a log whose every line is :data:`_CANONICAL`; None for any other log.

    Such a line is ASCII without a carriage return (text mode reads it as it is), its COB-ID's text is
    what ``f"{cob_id:03X}"`` writes and its data the text after ``#``: the bytes hashed are the same,
    in the same order (sha256 does not depend on how its input is cut into updates).
    """
    digest = hashlib.sha256()
    syncs = 0
    started = False
    sync_text = b"%03X" % _SYNC
    pdo_texts = {b"%03X" % cob_id for cob_id in _PDO_IDS}
    rest = b""
    with gzip.open(log, "rb") as source:
        while block := source.read(_BLOCK_BYTES):
            data = rest + block
            cut = data.rfind(b"\n") + 1
            whole, rest = data[:cut], data[cut:]
            lines = _CANONICAL.findall(whole)
            if len(lines) != whole.count(b"\n"):
                return None  # a line of another form: the general reading
            out: list[bytes] = []
            append = out.append
            for stamp, cob_text, payload in lines:
                if cob_text == sync_text:
                    started = True
                    syncs += 1
                    append(b"S%d\n" % round((float(stamp) - epoch_s) * 1e6))
                elif started and cob_text in pdo_texts:
                    append(cob_text + b"#" + payload + b"\n")
            digest.update(b"".join(out))
    if rest:
        return None  # a last line without its newline: the general reading
    return digest.hexdigest(), syncs


def _cyclic_stream_lines(log: Path, epoch_s: int) -> tuple[str, int]:
    """:func:`cyclic_stream` of any log, line by line (text mode; a line it cannot read raises)."""
    digest = hashlib.sha256()
    syncs = 0
    started = False
    with gzip.open(log, "rt", encoding="ascii") as lines:
        for line in lines:
            stamp, _, frame = line.split(" ", 3)[:3]
            cob_text, _, data = frame.partition("#")
            cob_id = int(cob_text, 16)
            if cob_id == _SYNC:
                started = True
                syncs += 1
                t_us = round((float(stamp[1:-1]) - epoch_s) * 1e6)
                digest.update(f"S{t_us}\n".encode())
            elif started and cob_id in _PDO_IDS:
                digest.update(f"{cob_id:03X}#{data}\n".encode())
    return digest.hexdigest(), syncs


def streams(out: Path) -> dict[str, Any]:
    """Every stream of the run in ``out`` (see the module docstring)."""
    out = Path(out)
    hil = json.loads((out / "hil.json").read_text(encoding="utf-8"))
    cyclic, syncs = cyclic_stream(out / "can.log.gz", int(hil["bus"]["traffic_log_epoch_s"]))
    found: dict[str, Any] = {"cyclic": cyclic, "syncs": syncs}
    for npz in sorted(out.glob("*.raw.npz")):
        with np.load(npz) as arrays:
            for name in arrays.files:
                a = arrays[name]
                found[f"arrays:{npz.name}:{name}"] = _sha(f"{a.dtype.str}{a.shape}".encode() + a.tobytes())
    for csv in sorted(out.glob("*.csv")):
        found[f"dataset:{csv.name}"] = _sha(csv.read_bytes())
    session = json.loads((out / "session.json").read_text(encoding="utf-8"))
    kept = {k: session.get(k) for k in _SESSION_FIELDS}
    model = session.get("model") or {}
    kept["model"] = {k: model.get(k) for k in _MODEL_FIELDS}
    found["session"] = _sha(json.dumps(kept, sort_keys=True).encode())
    events = []
    for line in (out / "audit.jsonl").read_text(encoding="utf-8").splitlines():
        event = json.loads(line)
        if event.get("job") in _BOOKKEEPING_JOBS:
            continue  # the session's summary kept current (issue 28): bookkeeping, not what the session did
        events.append({k: event.get(k) for k in _AUDIT_FIELDS})
    found["audit"] = _sha(json.dumps(events, sort_keys=True).encode())
    return found


if __name__ == "__main__":
    sys.stdout.write(json.dumps(streams(Path(sys.argv[1])), indent=1, sort_keys=True) + "\n")
