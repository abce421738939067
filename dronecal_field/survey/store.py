"""The survey's results on disk: a directory of parquet parts, one per finished task, keyed by (camera_id, strategy).

Layout of ``results.parquet/`` (a parquet *dataset*: pyarrow, DuckDB and
Spark read the directory as one table)::

    _survey.json              the configuration that defines the rows
    part-<n>-<uuid>.parquet   rows of one finished task

A part is written to a hidden temporary file and renamed into place, so a
survey killed at any instant leaves only whole parts; on restart the keys
already stored are skipped, so no row is computed twice. A restart with a
different configuration (other cameras, noise, trials) is refused rather
than mixed in; adding strategies is allowed.
"""

from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

import numpy as np

from dronecal_field.errors import InputError

MANIFEST = "_survey.json"
FORMAT_VERSION = 1

# Column order and types of every part (and of an exported single file).
COLUMNS: tuple[tuple[str, str], ...] = (
    ("camera_id", "int64"),
    ("strategy", "string"),
    ("status", "string"),
    ("message", "string"),
    ("focal_mm", "float64"),
    ("focal_px", "float64"),
    ("width_px", "int64"),
    ("height_px", "int64"),
    ("hfov_deg", "float64"),
    ("elevation_m", "float64"),
    ("tilt_deg", "float64"),
    ("distorted", "bool"),
    ("x_min_m", "float64"),
    ("x_max_m", "float64"),
    ("y_step_m", "float64"),
    ("n_heights", "int64"),
    ("heights_m", "string"),
    ("n_points", "int64"),
    ("trials", "int64"),
    ("rms_mean", "float64"),
    ("rms_std", "float64"),
    ("rms_max", "float64"),
    ("rms_p5", "float64"),
    ("rms_p50", "float64"),
    ("rms_p95", "float64"),
    ("rms_p99", "float64"),
    ("projection_error_px", "float64"),
    ("ground_projection_error_px", "float64"),
    ("ground_error_15m_cm", "float64"),
    ("speed_error_15m_kmh", "float64"),
    ("failed_trials", "int64"),
    ("compute_s", "float64"),
)


def schema():
    """The pyarrow schema of the result rows."""
    import pyarrow as pa

    return pa.schema([pa.field(name, pa.type_for_alias(kind)) for name, kind in COLUMNS])


def rows_to_table(rows: list[dict]):
    """A pyarrow Table of row dicts (missing fields are nulls; NaN floats become nulls)."""
    import pyarrow as pa

    def clean(v):
        if isinstance(v, float) and not np.isfinite(v):
            return None
        if isinstance(v, np.generic):
            return v.item()
        return v

    columns = {name: [clean(r.get(name)) for r in rows] for name, _ in COLUMNS}
    return pa.Table.from_pydict(columns, schema=schema())


class ResultStore:
    """A survey results directory: manifest, parts, the keys already computed."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    @property
    def manifest_path(self) -> Path:
        return self.path / MANIFEST

    def parts(self) -> list[Path]:
        """Finished parts, in name order."""
        if not self.path.is_dir():
            return []
        return sorted(self.path.glob("part-*.parquet"))

    def read_manifest(self) -> dict | None:
        if not self.manifest_path.is_file():
            return None
        return json.loads(self.manifest_path.read_text())

    def open(self, config: dict, strategies: list[str]) -> None:
        """Create the directory, or check that an existing one holds the same survey.

        Parameters
        ----------
        config : everything that defines a row's value (design, sampler, noise, trials, seeds)
        strategies : strategy names of this run (added to those already stored)
        """
        if self.path.exists() and not self.path.is_dir():
            raise InputError(f"{self.path} is a file, not a survey results directory: give --out a new name")
        old = self.read_manifest()
        if old is None:
            if self.path.is_dir() and any(self.path.iterdir()):
                raise InputError(f"{self.path} is not empty and holds no {MANIFEST}: give --out a new or empty directory")
            self.path.mkdir(parents=True, exist_ok=True)
            self._write_manifest({"format_version": FORMAT_VERSION, "config": config, "strategies": list(strategies)})
            return
        if old.get("config") != config:
            diff = sorted(k for k in set(config) | set(old.get("config", {})) if config.get(k) != old.get("config", {}).get(k))
            raise InputError(
                f"{self.path} holds a survey with other settings ({', '.join(diff)}): "
                "resume with the same flags or give --out a new directory"
            )
        merged = list(old.get("strategies", []))
        merged += [s for s in strategies if s not in merged]
        if merged != old.get("strategies"):
            self._write_manifest({**old, "strategies": merged})

    def _write_manifest(self, data: dict) -> None:
        tmp = self.path / f".{MANIFEST}.{uuid.uuid4().hex}.tmp"
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True))
        os.replace(tmp, self.manifest_path)

    def done_keys(self) -> set[tuple[int, str]]:
        """(camera_id, strategy) of every stored row (reads two columns of each part)."""
        import pyarrow.parquet as pq

        keys: set[tuple[int, str]] = set()
        for part in self.parts():
            t = read_part(part, columns=["camera_id", "strategy"])
            keys.update(zip(t.column("camera_id").to_pylist(), t.column("strategy").to_pylist()))
        return keys

    def write_part(self, rows: list[dict]) -> Path:
        """Store rows as one new part, atomically (write a hidden file, then rename it into place)."""
        import pyarrow.parquet as pq

        table = rows_to_table(rows)
        first = min(r["camera_id"] for r in rows) if rows else 0
        name = f"part-{first:06d}-{uuid.uuid4().hex[:12]}.parquet"
        tmp = self.path / f".{name}.tmp"
        pq.write_table(table, tmp, compression="zstd")
        os.replace(tmp, self.path / name)
        return self.path / name

    def clean_temporary(self) -> int:
        """Delete temporaries a killed run left behind; returns how many."""
        n = 0
        for tmp in self.path.glob(".part-*.tmp"):
            tmp.unlink(missing_ok=True)
            n += 1
        return n


def read_part(part: Path, **kwargs):
    """One stored part as a pyarrow Table; a damaged part (cut, overwritten) is an InputError naming it."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(part, **kwargs)
    except (pa.ArrowException, OSError) as exc:
        detail = str(exc).splitlines()[0][:120]
        raise InputError(f"survey part {part} is damaged ({detail}): delete it; re-running the survey with the same flags recomputes its rows") from None


def load_results(path: str | os.PathLike):
    """All rows of a survey: a results directory or a single exported parquet file, sorted by key.

    Returns
    -------
    pyarrow.Table with the columns of :data:`COLUMNS`
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    p = Path(path)
    if p.is_dir():
        parts = ResultStore(p).parts()
        if not parts:
            raise InputError(f"{p} holds no survey parts: run `dronecal-field survey --out {p}` first")
        table = pa.concat_tables([read_part(f, schema=schema()) for f in parts])
    elif p.is_file():
        try:
            table = pq.read_table(p)
        except (pa.ArrowInvalid, OSError) as exc:
            raise InputError(f"{p} is not a parquet file ({exc}): give the survey's --out directory or an exported .parquet") from None
        missing = [name for name, _ in COLUMNS if name not in table.column_names]
        if missing:
            raise InputError(f"{p} is not a survey result (no {', '.join(missing[:3])} column): give a file written by `dronecal-field survey`")
        table = table.select([name for name, _ in COLUMNS]).cast(schema())
    else:
        raise InputError(f"survey results {p} do not exist: run `dronecal-field survey --out {p}` first")
    return table.sort_by([("camera_id", "ascending"), ("strategy", "ascending")])


def read_config(path: str | os.PathLike) -> dict | None:
    """The survey configuration stored with results (a directory's manifest, or a file's parquet metadata)."""
    import pyarrow.parquet as pq

    p = Path(path)
    if p.is_dir():
        m = ResultStore(p).read_manifest()
        return None if m is None else m.get("config")
    if p.is_file():
        try:
            meta = pq.read_schema(p).metadata or {}
        except Exception:  # noqa: BLE001 - pyarrow raises several kinds for a damaged footer; load_results names it
            return None
        raw = meta.get(b"dronecal_survey")
        return None if raw is None else json.loads(raw).get("config")
    return None


def export_results(source: str | os.PathLike, dest: str | os.PathLike) -> Path:
    """Write all rows of a results directory to one parquet file, with the manifest in its metadata."""
    import pyarrow.parquet as pq

    table = load_results(source)
    manifest = ResultStore(source).read_manifest() if Path(source).is_dir() else None
    if manifest is not None:
        table = table.replace_schema_metadata({b"dronecal_survey": json.dumps(manifest).encode()})
    dest = Path(dest)
    tmp = dest.with_name(f".{dest.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:  # a hidden file renamed into place: an interrupted export leaves no half file under the name
        pq.write_table(table, tmp, compression="zstd")
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)
    return dest
