"""A study's folder: ``manifest.json``, ``results/part-*.parquet`` (one file per finished batch,
written under a hidden temporary name and renamed, so ``pyarrow.dataset.dataset(DIR/results)``
reads the whole study and never half a part), ``failures.parquet``, ``summary.md``, ``plots/`` and,
for ``[optimize]``, ``optuna.journal``.

Resume reads which (point, replicate) runs ``results/`` holds; a study file that differs from the
manifest's is refused naming the first field that changed.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import uuid
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from app.files import UserError, display_path
from core.study.point import METRICS
from core.study.spec import SCENARIO_AXIS, SPECIAL_AXES, StudySpec, flat_fields

MANIFEST = "manifest.json"
RESULTS = "results"
FAILURES = "failures.parquet"
SUMMARY = "summary.md"
PLOTS = "plots"
JOURNAL = "optuna.journal"
OWN = (MANIFEST, RESULTS, FAILURES, SUMMARY, PLOTS, JOURNAL)


def schema(spec: StudySpec, failures: bool = False) -> pa.Schema:
    """The results' columns (failures: the same head, then ``error`` and ``worker``)."""
    fields = [pa.field("point", pa.string()), pa.field("replicate", pa.int64()), pa.field("seed", pa.int64())]
    for a in spec.axes:
        if a.name == SCENARIO_AXIS:
            fields.append(pa.field(a.name, pa.string()))
        elif a.integer or SPECIAL_AXES.get(a.name, (0, 0, "", False))[3]:
            fields.append(pa.field(a.name, pa.int64()))
        else:
            fields.append(pa.field(a.name, pa.float64()))
    if failures:
        return pa.schema([*fields, pa.field("error", pa.string()), pa.field("worker", pa.string())])
    kinds = {"bool": pa.bool_(), "int": pa.int64(), "float": pa.float64()}
    fields += [pa.field(name, kinds[kind]) for name, (kind, _) in METRICS.items()]
    fields += [pa.field("wall_s", pa.float64()), pa.field("worker", pa.string())]
    return pa.schema(fields)


def code_version() -> dict[str, str]:
    """The code's version and the numeric libraries' (what a result depends on)."""
    import importlib.metadata as md

    versions = {}
    for name in ("omniformation", "numpy", "numba", "scipy", "dask", "distributed", "pyarrow", "optuna"):
        try:
            versions[name] = md.version(name)
        except md.PackageNotFoundError:
            versions[name] = "not installed"
    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=10, check=False).stdout.strip()
    except (OSError, subprocess.TimeoutExpired):
        commit = ""
    versions["commit"] = commit or "unknown"
    return versions


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


class StudyFolder:
    """The folder ``out`` of one study."""

    def __init__(self, out: Path) -> None:
        self.out = out
        self.results = out / RESULTS
        self._session = uuid.uuid4().hex[:8]
        self._parts = 0

    # ---------------------------------------------------------------- opening
    def open(self, spec: StudySpec, study_path: Path, overwrite: bool) -> bool:
        """Make or check the folder; True when it already held this study (a resume)."""
        out = self.out
        if out.exists() and not out.is_dir():
            raise UserError(f"--out {display_path(out)}: exists and is not a folder")
        manifest = out / MANIFEST
        if out.exists() and overwrite:
            for name in OWN:
                p = out / name
                if p.is_dir():
                    shutil.rmtree(p)
                elif p.exists():
                    p.unlink()
        elif manifest.exists():
            self._check_same(spec, study_path, manifest)
            self.results.mkdir(exist_ok=True)
            return True
        elif out.exists() and any(out.iterdir()):
            raise UserError(f"--out {display_path(out)}: a folder with files and no {MANIFEST}: not a study's folder"
                            " (give a new or empty folder)")
        try:
            self.results.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(f"--out {display_path(out)}: cannot make the folder: {exc.strerror or exc}") from None
        body = {"study_file": study_path.name, "study_sha256": sha256(spec.text), "study_text": spec.text,
                "scenarios": {s.name: s.text for s in spec.scenarios}, "version": code_version(),
                "points": spec.points, "replicates": spec.replicates, "runs": spec.runs,
                "axes": list(spec.axis_names), "feedback": spec.feedback,
                "metrics": {k: v[1] for k, v in METRICS.items()}}
        _write_atomic(manifest, (json.dumps(body, indent=2) + "\n").encode())
        return False

    def manifest(self) -> dict[str, Any]:
        path = self.out / MANIFEST
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise UserError(f"{display_path(self.out)}: no {MANIFEST}: not a study's folder") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
            raise UserError(f"{display_path(path)}: not a study manifest ({type(exc).__name__})") from None
        if not isinstance(data, dict) or not isinstance(data.get("study_text"), str):
            raise UserError(f"{display_path(path)}: not a study manifest (no study_text)")
        return data

    def _check_same(self, spec: StudySpec, study_path: Path, manifest: Path) -> None:
        old = self.manifest()
        if old.get("study_sha256") == sha256(spec.text) and old.get("study_text") == spec.text:
            return
        try:
            before = dict(flat_fields(old["study_text"], "manifest"))
        except ValueError:
            before = {}
        now = flat_fields(spec.text, str(study_path))
        changed = next(((k, v) for k, v in now if before.get(k, _MISSING) != v), None)
        if changed is None:
            gone = next((k for k in before if k not in dict(now)), None)
            what = f"{gone} was removed" if gone else "its text changed"
        else:
            k, v = changed
            was = before.get(k, _MISSING)
            what = f"{k} = {v!r} (was {'absent' if was is _MISSING else repr(was)})"
        raise UserError(f"{display_path(study_path)}: differs from the study in {display_path(self.out)}: {what};"
                        " give --overwrite to start it again, or another --out")

    # ---------------------------------------------------------------- reading
    def dataset(self) -> ds.Dataset:
        return ds.dataset(str(self.results), format="parquet")

    def done(self) -> set[tuple[str, int]]:
        """The (point, replicate) runs already in results/."""
        if not self.results.exists() or not any(self.results.glob("part-*.parquet")):
            return set()
        try:
            table = self.dataset().to_table(columns=["point", "replicate"])
        except (pa.ArrowInvalid, OSError) as exc:
            raise UserError(f"{display_path(self.results)}: a part cannot be read ({str(exc).splitlines()[0][:200]});"
                            " move the damaged part away and run again: its runs are made again") from None
        return set(zip(table.column("point").to_pylist(), table.column("replicate").to_pylist()))

    def table(self) -> pa.Table:
        if not self.results.exists() or not any(self.results.glob("part-*.parquet")):
            return pa.table({})
        try:
            return self.dataset().to_table()
        except (pa.ArrowInvalid, OSError) as exc:
            raise UserError(f"{display_path(self.results)}: a part cannot be read ({str(exc).splitlines()[0][:200]})") from None

    def failures(self) -> list[dict[str, Any]]:
        path = self.out / FAILURES
        if not path.exists():
            return []
        try:
            rows: list[dict[str, Any]] = pq.read_table(path).to_pylist()
            return rows
        except (pa.ArrowInvalid, OSError) as exc:
            raise UserError(f"{display_path(path)}: cannot be read ({str(exc).splitlines()[0][:200]}); move it away") from None

    # ---------------------------------------------------------------- writing
    def write_part(self, spec: StudySpec, rows: list[dict[str, Any]]) -> Path:
        """One finished batch as a part of results/ (a hidden temporary name, then renamed)."""
        self._parts += 1
        path = self.results / f"part-{self._session}-{self._parts:06d}.parquet"
        tmp = self.results / f".{path.name}.tmp"
        pq.write_table(pa.Table.from_pylist(rows, schema=schema(spec)), tmp)
        os.replace(tmp, path)
        return path

    def write_failures(self, spec: StudySpec, rows: list[dict[str, Any]]) -> None:
        path = self.out / FAILURES
        if not rows:
            if path.exists():
                path.unlink()
            return
        tmp = self.out / f".{FAILURES}.tmp"
        pq.write_table(pa.Table.from_pylist(rows, schema=schema(spec, failures=True)), tmp)
        os.replace(tmp, path)


_MISSING = object()
