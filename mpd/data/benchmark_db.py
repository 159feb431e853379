"""Benchmark results in OMPL's benchmark database format (SQLite), the one ``ompl_benchmark_statistics.py`` writes
and Planner Arena (``plannerarena``) reads.

Tables: ``experiments`` (one row per experiment: name, total time, time and memory limits, run count, version,
host, CPU, date, seed, setup; extra columns are experiment parameters), ``plannerConfigs`` (name, settings),
``enums`` (the names of an ENUM attribute's values, e.g. ``status``), ``runs`` (id, experimentid, plannerid, then one
column per run attribute) and ``progress`` (runid, time, then progress attributes). Planner Arena takes the run
attributes from the columns after the first three of ``runs`` and the experiment parameters from the columns after
the first twelve of ``experiments``, so both keep OMPL's column order.

The database is written whole, to a temporary name, and renamed: a killed writer leaves the previous one.
"""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

# OMPL's ompl::base::PlannerStatus, in its order (the value stored in the ``status`` column)
STATUS = (
    "Unknown status",
    "Invalid start",
    "Invalid goal",
    "Unrecognized goal type",
    "Timeout",
    "Approximate solution",
    "Exact solution",
    "Crash",
    "Abort",
    "Infeasible",
)
_TYPES = {"REAL", "INTEGER", "BOOLEAN", "ENUM", "VARCHAR(128)", "TEXT"}

_SCHEMA = """
CREATE TABLE experiments
    (id INTEGER PRIMARY KEY AUTOINCREMENT, name VARCHAR(512), totaltime REAL, timelimit REAL, memorylimit REAL,
    runcount INTEGER, version VARCHAR(128), hostname VARCHAR(1024), cpuinfo TEXT, date DATETIME, seed VARCHAR(24),
    setup TEXT);
CREATE TABLE plannerConfigs (id INTEGER PRIMARY KEY AUTOINCREMENT, name VARCHAR(512) NOT NULL, settings TEXT);
CREATE TABLE enums (name VARCHAR(512), value INTEGER, description TEXT, PRIMARY KEY (name, value));
CREATE TABLE runs
    (id INTEGER PRIMARY KEY AUTOINCREMENT, experimentid INTEGER, plannerid INTEGER,
    FOREIGN KEY (experimentid) REFERENCES experiments(id) ON DELETE CASCADE,
    FOREIGN KEY (plannerid) REFERENCES plannerConfigs(id) ON DELETE CASCADE);
CREATE TABLE progress
    (runid INTEGER, time REAL, PRIMARY KEY (runid, time), FOREIGN KEY (runid) REFERENCES runs(id) ON DELETE CASCADE);
"""


@dataclass
class Experiment:
    """One experiment (a problem, or a set of problems with one run each) and its runs.

    ``attributes``: run attribute name -> SQL type (REAL, INTEGER, BOOLEAN, ENUM, VARCHAR(128), TEXT), in column order;
    ``runs``: (planner name, planner settings, {attribute: value}) each; ``parameters``: experiment parameters
    (extra columns of ``experiments``), name -> value."""

    name: str
    timelimit: float
    version: str
    hostname: str = ""
    cpuinfo: str = ""
    date: str = ""
    seed: int = 0
    setup: str = ""
    totaltime: float = 0.0
    memorylimit: float = 0.0
    attributes: dict[str, str] = field(default_factory=dict)
    runs: list[tuple[str, str, dict]] = field(default_factory=list)
    parameters: dict[str, str | int | float] = field(default_factory=dict)


def _column(name: str) -> str:
    if not name.replace("_", "").isalnum():
        raise ValueError(f"column name {name!r}: letters, digits and '_' only")
    return name


def write(path: str | Path, experiments: Sequence[Experiment], enums: dict[str, Sequence[str]] | None = None) -> Path:
    """Write ``experiments`` to a new benchmark database at ``path`` (replacing it). ``enums``: ENUM attribute ->
    the names of its values 0, 1, ... (``status`` gets OMPL's planner statuses unless given)."""
    enums = {"status": STATUS, **(enums or {})}
    attrs, params = _columns(experiments, enums)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    conn = sqlite3.connect(tmp)
    try:
        c = conn.cursor()
        c.execute("PRAGMA FOREIGN_KEYS = ON")
        c.executescript(_SCHEMA)
        for k, t in attrs.items():
            c.execute(f"ALTER TABLE runs ADD {k} {t}")
        for k, t in params.items():
            c.execute(f"ALTER TABLE experiments ADD {k} {t}")
        for name in sorted(k for k, t in attrs.items() if t == "ENUM"):
            c.executemany("INSERT INTO enums VALUES (?, ?, ?)", [(name, i, d) for i, d in enumerate(enums[name])])
        planners: dict[tuple[str, str], int] = {}
        for e in experiments:
            cols = ["name", "totaltime", "timelimit", "memorylimit", "runcount", "version", "hostname", "cpuinfo"]
            cols += ["date", "seed", "setup", *e.parameters]
            vals = [e.name, e.totaltime, e.timelimit, e.memorylimit, len(e.runs), e.version, e.hostname, e.cpuinfo]
            vals += [e.date, str(e.seed), e.setup, *e.parameters.values()]
            c.execute(f"INSERT INTO experiments ({','.join(cols)}) VALUES ({','.join('?' * len(vals))})", vals)
            exp_id = c.lastrowid
            for planner, settings, values in e.runs:
                key = (planner, settings)
                if key not in planners:
                    c.execute("INSERT INTO plannerConfigs (name, settings) VALUES (?, ?)", key)
                    planners[key] = c.lastrowid
                names = ["experimentid", "plannerid", *values]
                row = [exp_id, planners[key], *(_sql_value(v) for v in values.values())]
                c.execute(f"INSERT INTO runs ({','.join(names)}) VALUES ({','.join('?' * len(row))})", row)
        conn.commit()
    except BaseException:
        conn.close()
        tmp.unlink(missing_ok=True)
        raise
    conn.close()
    os.replace(tmp, path)
    return path


def _columns(experiments: Sequence[Experiment], enums: dict) -> tuple[dict[str, str], dict[str, str]]:
    """The run attributes' and experiment parameters' columns (name -> SQL type), checked before anything is
    written."""
    attrs: dict[str, str] = {}
    params: dict[str, str] = {}
    for e in experiments:
        for k, t in e.attributes.items():
            if t not in _TYPES:
                raise ValueError(f"attribute {k!r}: type {t!r} (one of {sorted(_TYPES)})")
            if attrs.setdefault(_column(k), t) != t:
                raise ValueError(f"attribute {k!r} has types {attrs[k]} and {t}")
            if t == "ENUM" and k not in enums:
                raise ValueError(f"ENUM attribute {k!r} has no value names (give enums={{{k!r}: [...]}})")
        for k, v in e.parameters.items():
            params.setdefault(
                _column(k), "REAL" if isinstance(v, float) else "INTEGER" if isinstance(v, int) else "TEXT"
            )
        for planner, _settings, values in e.runs:
            unknown = set(values) - set(e.attributes)
            if unknown:
                raise ValueError(f"experiment {e.name!r}, {planner}: values of undeclared attributes {sorted(unknown)}")
    return attrs, params


def _sql_value(v):
    """None for missing or non-finite numbers (OMPL's reader stores nan and inf as NULL), ints for booleans."""
    if v is None:
        return None
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, float) and (v != v or v in (float("inf"), float("-inf"))):
        return None
    return v
