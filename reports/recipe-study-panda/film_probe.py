"""The context path of trained priors: the context embedding's size and spread over contexts, and the size of each
FiLM layer's scale, on 1024 random normalized EE-goal contexts (a checkpoint's raw and EMA weights).

    python reports/recipe-study-panda/film_probe.py <model.pt or last.pt> ...

Per checkpoint and weight set: the embedding's mean magnitude and its spread (the std over contexts, averaged over
features), the step embedding's magnitude (step 10), and per residual block the FiLM scale's mean magnitude / its
spread over contexts. A scale near or below -1 turns a block's features off ((1 + scale) multiplies them).
"""

from __future__ import annotations

import sys

import scipy.stats
import torch

from mpd.models.checkpoint import build_network, read_checkpoint
from mpd.schema import from_dict
from mpd.tasks.spec import ModelSpec


def contexts(n: int = 1024, dof: int = 7) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    rot = scipy.stats.special_ortho_group.rvs(3, size=n, random_state=0)
    return {
        "q_start": torch.rand(n, dof, generator=g) * 2 - 1,
        "ee_pos": torch.rand(n, 3, generator=g) * 2 - 1,
        "ee_rot": torch.as_tensor(rot).float(),
    }


def main(paths: list[str]) -> None:
    torch.set_num_threads(1)
    for path in paths:
        ck = read_checkpoint(path)
        spec = from_dict(ModelSpec, ck["model_spec"], source=path, where="model_spec")
        net = build_network(ck["kind"], int(ck["dof"]), int(ck["horizon"]), ck["context_kind"], spec)
        ctx = contexts(dof=int(ck["dof"]))
        for key in ("weights", "ema_weights"):
            net.load_state_dict(ck[key])
            with torch.no_grad():
                emb = net.context_encoder(ctx)
                te = net.unet.time_mlp(torch.full((emb.shape[0],), 10))
                cond = torch.cat([te, emb], -1)
                films = [m.film(cond).chunk(2, dim=1)[0] for m in net.unet.modules() if hasattr(m, "film")]
            blocks = " ".join(f"{float(s.abs().mean()):.2f}/{float(s.std(0).mean()):.2f}" for s in films)
            print(
                f"{ck['identity'][:8]} {key:11s} embedding |.| {float(emb.abs().mean()):.3f} spread "
                f"{float(emb.std(0).mean()):.3f}; step |.| {float(te.abs().mean()):.3f}; FiLM scale per block: {blocks}"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
