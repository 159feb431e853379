"""Static figures: every figure function writes a non-empty PNG (and a PDF on request) for 2-D tasks and the
Panda. What the figures look like is checked by eye; these tests keep them running."""

from __future__ import annotations

import pytest
import torch

from mpd.tasks import load_task
from mpd.trajectory import make_parametrization
from mpd.viz import scene

PNG = b"\x89PNG\r\n\x1a\n"


def _batch(task, B: int, seed: int = 0):
    """B noisy B-spline trajectories between two fixed configurations, and a validity mask with both kinds."""
    par = make_parametrization(task)
    g = torch.Generator().manual_seed(seed)
    qs, qg = task.robot.random_q(2, g)
    line = qs + torch.as_tensor(par.param_phases())[:, None] * (qg - qs)
    w = line + 0.1 * torch.randn(B, par.n_params, task.dof, generator=g, dtype=torch.float64)
    d = par.dense(par.free_rows(w), qs.expand(B, -1), None if task.ee_goal else qg.expand(B, -1))
    valid = torch.arange(B) % 3 != 0
    return d, valid


def _png(path) -> None:
    data = path.read_bytes()
    assert data[:8] == PNG and len(data) > 5_000


@pytest.mark.parametrize(
    "name", ["EnvSimple2D-RobotPointMass2D", "EnvPlanar4Link-RobotPlanar4Link", "EnvWarehouse-RobotPanda"]
)
def test_every_figure_writes_a_png(tmp_path, name):
    t = load_task(name)
    env = t.env(extra_objects=True, rotation_deg=15.0)
    B = 6 if t.dim == 2 else 3
    d, valid = _batch(t, B)
    figs = {
        "task": scene.task_figure(t, env, d.q[0, 0], out=tmp_path / "task.png"),
        "paths": scene.draw_paths_figure(t, env, d.q, valid, out=tmp_path / "paths.png", title="samples"),
        "traj": scene.trajectory_figure(t, env, d.q, d.dq_dt, d.ddq_dt2, valid, out=tmp_path / "traj.png"),
        "denoise": scene.denoising_figure(
            t,
            env,
            [("i = 5", d.q * 1.05, valid & False), ("i = 0", d.q, valid)],
            out=tmp_path / "denoise.png",
        ),
    }
    for key in figs:
        _png(tmp_path / f"{key}.png")
    assert len(figs["traj"].axes) == 1 + 3 * t.dof
    assert len(figs["denoise"].axes) == 2


def test_pdf_also_writes_png_and_validity_optional(tmp_path):
    t = load_task("EnvPlanar2Link-RobotPlanar2Link")
    d, _ = _batch(t, 4)
    out = tmp_path / "sub" / "paths.pdf"
    scene.draw_paths_figure(t, t.env(), d.q.numpy(), None, out=out, max_paths=2)
    assert out.read_bytes()[:5] == b"%PDF-" and out.stat().st_size > 5_000
    _png(out.with_suffix(".png"))
    assert not list(out.parent.glob(".*tmp"))  # written under a temporary name, then renamed


def test_draw_on_own_axes():
    """The drawing functions work on axes the caller made (a 2-D one and a 3-D one side by side)."""
    from matplotlib.figure import Figure

    fig = Figure()
    t2, t3 = load_task("EnvPlanar2Link-RobotPlanar2Link"), load_task("EnvSpheres3D-RobotPanda")
    ax2, ax3 = fig.add_subplot(121), fig.add_subplot(122, projection="3d")
    scene.draw_environment(ax2, t2.env())
    scene.draw_robot(ax2, t2, torch.zeros(2), color="C2")
    scene.draw_environment(ax3, t3.env(True), workspace=False)
    scene.draw_robot(ax3, t3, torch.zeros(7))
    assert ax2.patches and ax3.collections
    assert ax3.get_xlim() == tuple(t3.env().workspace[0][:1]) + tuple(t3.env().workspace[1][:1])


def test_bad_input():
    t = load_task("EnvSimple2D-RobotPointMass2D")
    d, valid = _batch(t, 4)
    with pytest.raises(ValueError, match="valid has 3 entries"):
        scene.draw_paths_figure(t, t.env(), d.q, valid[:3])
    with pytest.raises(ValueError, match="at least one"):
        scene.denoising_figure(t, t.env(), [])


def test_many_samples_keep_the_trajectory_pdf_small(tmp_path):
    """A batch of 1000 (the batch-size experiments) once wrote an 11 MB PDF: above RASTER_ABOVE samples the
    joint-space lines are drawn as an image inside the PDF; few samples stay vector lines."""
    from matplotlib.collections import LineCollection

    t = load_task("EnvPlanar2Link-RobotPlanar2Link")
    for n, rasterized in ((8, False), (scene.RASTER_ABOVE + 1, True)):
        d, valid = _batch(t, n)
        out = tmp_path / f"traj{n}.pdf"
        fig = scene.trajectory_figure(t, t.env(), d.q, d.dq_dt, d.ddq_dt2, valid, out=out)
        joint = [c for ax in fig.axes[1:] for c in ax.collections if isinstance(c, LineCollection)]
        assert joint and all(c.get_rasterized() == rasterized for c in joint)
    d, valid = _batch(t, 1000)
    out = tmp_path / "traj1000.pdf"
    scene.trajectory_figure(t, t.env(), d.q, d.dq_dt, d.ddq_dt2, valid, out=out)
    assert out.stat().st_size < 1_000_000  # 2.2 MB with vector lines, 0.1 MB rasterized
