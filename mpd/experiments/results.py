"""Results of a run: one row per (cell, context), appended as it is produced, never lost.

Each cell has a JSON-lines file ``parts/<cell_key>.jsonl``; a row is one line written with a single ``write`` and
flushed to disk before the next unit starts, so a killed runner loses at most the row being computed, and a
half-written last line (the only possible damage) is ignored on reading. ``results.parquet`` (one long table:
parameter, metric, timing and provenance columns) is rebuilt from the parts, written to a temporary name and
renamed.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import pandas as pd

from mpd.schema import ConfigError


class RowStore:
    def __init__(self, run_dir: Path):
        self.dir = Path(run_dir) / "parts"
        self.dir.mkdir(parents=True, exist_ok=True)

    def _path(self, cell_key: str) -> Path:
        return self.dir / f"{cell_key}.jsonl"

    def rows(self, cell_key: str | None = None) -> list[dict]:
        paths = [self._path(cell_key)] if cell_key else sorted(self.dir.glob("*.jsonl"))
        out = []
        for p in paths:
            if not p.exists():
                continue
            for line in p.read_text().splitlines():
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    continue  # a line cut by a kill: that unit was not finished and will be recomputed
        return out

    def done(self, cell_key: str) -> set[int]:
        return {int(r["context_index"]) for r in self.rows(cell_key)}

    def append(self, cell_key: str, row: dict) -> None:
        line = json.dumps(row, default=_jsonable) + "\n"
        path = self._path(cell_key)
        # a kill may have left a partial last line: start the new row on a fresh line
        if path.exists() and path.stat().st_size and not path.read_bytes().endswith(b"\n"):
            line = "\n" + line
        with open(path, "a") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())

    def table(self) -> pd.DataFrame:
        rows = self.rows()
        if not rows:
            return pd.DataFrame()
        df = pd.DataFrame(rows)
        return df.sort_values(["cell_key", "context_index"], kind="stable").reset_index(drop=True)


def _jsonable(x):
    if hasattr(x, "item"):
        return x.item()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serializable: {type(x).__name__}")


def write_parquet(df: pd.DataFrame, path: Path) -> Path:
    path = Path(path)
    tmp = path.with_suffix(".parquet.tmp")
    df.to_parquet(tmp, index=False)
    os.replace(tmp, path)
    return path


def write_json(obj, path: Path) -> None:
    path = Path(path)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=_jsonable, sort_keys=False) + "\n")
    os.replace(tmp, path)


def read_results(run_dir: Path) -> pd.DataFrame:
    """The run's table: the Parquet file when it is complete and no part is newer, else rebuilt from the parts (a
    part replaced by another run's of the same size, when runs made in pieces are merged, is newer than the table)."""
    run_dir = Path(run_dir)
    p = run_dir / "results.parquet"
    store = RowStore(run_dir)
    n_parts = len(store.rows())
    if p.exists():
        newest_part = max((f.stat().st_mtime for f in store.dir.glob("*.jsonl")), default=0.0)
        try:
            df = pd.read_parquet(p)
        except Exception as e:  # truncated or overwritten; the parts, when the run has them, hold the same rows
            why = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
            if n_parts == 0:
                raise ConfigError(p, "", f"does not read back ({why}); no parts to rebuild it from") from None
            warnings.warn(f"{p}: does not read back ({why}); the table is rebuilt from the run's parts", stacklevel=2)
            return store.table()
        if len(df) >= n_parts and p.stat().st_mtime >= newest_part:
            return df
    return store.table()
