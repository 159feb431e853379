"""Specs that extend specs (``extends = "NAME"`` plus the fields that differ): resolved at load time, hashed by their
resolved content, so that a spec written as a difference has the identity (and the cells) of the copy it replaces."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import pytest

from mpd.experiments.spec import SPEC_DIR, load_spec
from mpd.schema import ConfigError, read_toml

ROOT = Path(__file__).resolve().parents[1]
TASK = "EnvSimple2D-RobotPointMass2D"
BASE = f"""
name = "base"
description = "the parent"
n_contexts = 4
n_samples = 16
[axes]
task = ["{TASK}"]
method = ["gp-cost", "mpd"]
extra_objects = [false, true]
[[exclude]]
method = "mpd"
extra_objects = true
[tasks."{TASK}"]
dataset = "tiny"
profile = "cpu"
"""


def _write(root: Path, name: str, text: str) -> Path:
    p = root / f"{name}.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_an_extending_spec_is_the_copy_it_replaces(tmp_path):
    _write(tmp_path, "base", BASE)
    copy = BASE.replace('name = "base"', 'name = "child"').replace('profile = "cpu"', 'profile = "gpu"')
    copy = copy.replace('"mpd"]', '"mpd", "dprior"]')
    full = load_spec(_write(tmp_path, "copy", copy))
    child = load_spec(
        _write(
            tmp_path,
            "child",
            f"""
            extends = "base.toml"
            name = "child"
            [axes]
            method = ["gp-cost", "mpd", "dprior"]
            [tasks."{TASK}"]
            profile = "gpu"
            """,
        )
    )
    assert child.raw == full.raw and "extends" not in child.raw
    assert child.hash == full.hash
    assert child.cells() == full.cells()
    assert child.data.tasks[TASK].dataset == "tiny"  # a table's other fields come from the parent
    assert child.data.description == "the parent"
    assert child.hash != load_spec(tmp_path / "base.toml").hash


def test_extends_chains(tmp_path):
    _write(tmp_path, "base", BASE)
    _write(tmp_path, "middle", 'extends = "base.toml"\nname = "middle"\nn_samples = 8\n')
    last = load_spec(_write(tmp_path, "last", 'extends = "middle.toml"\nname = "last"\nn_contexts = 2\n'))
    assert (last.data.n_samples, last.data.n_contexts, last.name) == (8, 2, "last")


@pytest.mark.parametrize(
    ("files", "where", "message"),
    [
        ({"a": 'extends = "nope-spec"\nname = "a"\n'}, "extends", "unknown spec 'nope-spec'"),
        ({"a": 'extends = "base.toml"\n'}, "name", "needs its own name"),
        ({"a": 'extends = 3\nname = "a"\n'}, "extends", "is not a spec name"),
        (
            {"a": 'extends = "b.toml"\nname = "a"\n', "b": 'extends = "a.toml"\nname = "b"\n'},
            "extends",
            "cycle: a -> b -> a",
        ),
        ({"a": 'extends = "a.toml"\nname = "a"\n'}, "extends", "cycle: a -> a"),
    ],
)
def test_bad_extends_is_a_clear_error(tmp_path, files, where, message):
    _write(tmp_path, "base", BASE)
    for name, text in files.items():
        _write(tmp_path, name, text)
    with pytest.raises(ConfigError) as e:
        load_spec(tmp_path / "a.toml")
    msg = str(e.value)  # the file whose field is wrong (in a cycle: the one that closes it)
    assert str(tmp_path) in msg and f".toml: {where}" in msg and message in msg, msg


EXTENDING = sorted(p.stem for p in SPEC_DIR.glob("*.toml") if "extends" in read_toml(p))


def test_shipped_specs_extend_others():
    assert len(EXTENDING) >= 5


@pytest.mark.parametrize("name", EXTENDING)
def test_extending_specs_keep_their_reports_provenance(name):
    """A shipped spec written with ``extends`` resolves to exactly the spec its committed report was run from."""
    manifest = ROOT / "reports" / name / "manifest.json"
    if not manifest.exists():
        pytest.skip(f"no committed report of {name}")
    man = json.loads(manifest.read_text())
    spec = load_spec(name)
    assert spec.raw == man["spec"]
    assert spec.hash == man["spec_hash"]
