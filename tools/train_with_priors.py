"""Train a small network with the method's priors as losses (weak supervision, no ground truth).

A fully convolutional network (about 0.1 M parameters) predicts ``log R`` and ``log S`` from
crops of MIT-Berkeley training objects (their ``diffuse`` and ``light01..04`` inputs, at a
reduced resolution) and of synthetic Mondrian scenes. It is trained twice with the same seed,
crops and schedule:

1. with the reconstruction loss ``‖R·S − I‖²`` only;
2. with :class:`torchiid.losses.PriorLoss` (reconstruction plus the shading and reflectance
   priors, their image-derived weights precomputed once per crop without gradient).

Neither run sees a ground-truth layer. Both are scored by MIT LMSE (:func:`torchiid.mit_lmse`)
on held-out objects at the same reduced resolution, next to two trivial baselines.

Usage::

    OMP_NUM_THREADS=2 python tools/train_with_priors.py ../shared/data/mit-berkeley \
        [--steps 300] [--test apple,frog1,phone]
"""

from __future__ import annotations

import torchiid.openmp  # noqa: F401  (before torch: see torchiid/openmp.py)

import argparse
import time

import torch
import torch.nn.functional as F
from torch import nn

from torchiid.eval import mit_lmse
from torchiid.eval.datasets import MITDataset
from torchiid.io import load_image
from torchiid.losses import PriorLoss
from torchiid.params import Parameters
from torchiid.synthetic import mondrian

CROP = 48
MAX_SIDE = 128


class SmallNet(nn.Module):
    """A small encoder-decoder: image -> (log R (3), log S (1))."""

    def __init__(self, width: int = 32) -> None:
        super().__init__()

        def block(i: int, o: int) -> nn.Sequential:
            return nn.Sequential(
                nn.Conv2d(i, o, 3, padding=1), nn.GELU(), nn.Conv2d(o, o, 3, padding=1), nn.GELU()
            )

        self.enc1 = block(4, width)
        self.enc2 = block(width, 2 * width)
        self.dec = block(3 * width, width)
        self.head = nn.Conv2d(width, 4, 1)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Return ``(log R, log S)``: two heads, ``log R = log I − log S + δ``."""
        log_i = image.clamp_min(1e-4).log()
        x = torch.cat([log_i, log_i.mean(1, keepdim=True)], 1)
        a = self.enc1(x)
        b = self.enc2(F.avg_pool2d(a, 2))
        up = F.interpolate(b, size=a.shape[-2:], mode="bilinear", align_corners=False)
        out = self.head(self.dec(torch.cat([a, up], 1)))
        log_s, delta = out[:, :1], out[:, 1:]
        # δ is free: only the loss ties R · S to the image
        return log_i - log_s + delta, log_s


def shrink(x: torch.Tensor) -> torch.Tensor:
    h, w = x.shape[-2:]
    f = MAX_SIDE / max(h, w)
    size = (max(CROP, round(h * f)), max(CROP, round(w * f)))
    return F.interpolate(x[None].float(), size=size, mode="area")[0]


def crops(root: str, train: list[str], per_image: int, gen: torch.Generator):
    imgs, masks = [], []
    ds = MITDataset(root, train)
    for name in ds.ids:
        folder = ds.root / name
        m = shrink(ds[ds.ids.index(name)].mask.float()) > 0.5
        for f in ["diffuse.png", "light01.png", "light02.png", "light03.png", "light04.png"]:
            img = shrink(load_image(folder / f, linear=True).image)
            img = img / img.amax().clamp_min(1e-6)
            h, w = img.shape[-2:]
            for _ in range(per_image):
                for _try in range(20):
                    y = int(torch.randint(0, h - CROP + 1, (1,), generator=gen))
                    x = int(torch.randint(0, w - CROP + 1, (1,), generator=gen))
                    mc = m[:, y : y + CROP, x : x + CROP]
                    if mc.float().mean() > 0.6:
                        break
                imgs.append(img[:, y : y + CROP, x : x + CROP] * mc)
                masks.append(mc)
    n_syn = len(imgs) // 2
    syn = mondrian(
        CROP, CROP, batch=n_syn, seed=int(torch.randint(0, 1 << 30, (1,), generator=gen))
    )
    for i in range(n_syn):
        imgs.append(syn.image[i])
        masks.append(torch.ones(1, CROP, CROP, dtype=torch.bool))
    return torch.stack(imgs), torch.stack(masks)


def evaluate(net: nn.Module | None, samples) -> float:
    scores = []
    for s in samples:
        img, mask = shrink(s.image)[None], (shrink(s.mask.float()) > 0.5)[None]
        r_true, s_true = shrink(s.reflectance)[None], shrink(s.shading)[None]
        img = img * mask
        if net is None:  # R = I, S = 1
            r, sh = img, torch.ones_like(img[:, :1])
        elif net == "flat":  # S = intensity, R = I / S (all in the shading)
            sh = img.mean(1, keepdim=True).clamp_min(1e-4)
            r = img / sh
        else:
            with torch.no_grad():
                lr, ls = net(img)
            r, sh = lr.exp() * mask, ls.exp() * mask
        scores.append(float(mit_lmse(r_true, s_true, r, sh, mask)))
    return sum(scores) / len(scores)


def train(images, masks, priors, use_priors: bool, steps: int, seed: int) -> nn.Module:
    torch.manual_seed(seed)
    net = SmallNet()
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    loss_fn = PriorLoss(PARAMS, log_space=True, use_shading=use_priors, use_reflectance=use_priors)
    gen = torch.Generator().manual_seed(seed)
    batch = 8
    for step in range(steps):
        idx = torch.randint(0, len(images), (batch,), generator=gen)
        total = 0.0
        opt.zero_grad()
        for i in idx.tolist():  # the priors are per crop: one crop at a time, grads summed
            img, m = images[i : i + 1], masks[i : i + 1]
            lr, ls = net(img)
            loss = loss_fn(img, lr, ls, priors[i] if use_priors else None, m) / batch
            loss.backward()
            total += loss.item()
        opt.step()
        if step % 50 == 0 or step == steps - 1:
            print(f"  step {step:4d} loss {total:.5f}", flush=True)
    return net


PARAMS = Parameters().replace(patch_size=16, patch_stride=8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", help="MIT-Berkeley folder (one folder per object)")
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--per-image", type=int, default=2, help="crops per training image")
    ap.add_argument("--test", default="apple,frog1,phone", help="held-out objects")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    test = args.test.split(",")
    every = MITDataset(args.root).ids
    train_ids = [o for o in every if o not in test]
    gen = torch.Generator().manual_seed(args.seed)
    t0 = time.perf_counter()
    images, masks = crops(args.root, train_ids, args.per_image, gen)
    loss_fn = PriorLoss(PARAMS)
    priors = [loss_fn.priors(images[i : i + 1], mask=masks[i : i + 1]) for i in range(len(images))]
    print(
        f"{len(images)} crops {CROP}x{CROP} from {train_ids} + Mondrians, priors built in "
        f"{time.perf_counter() - t0:.1f} s; held out: {test}"
    )
    print(f"network parameters: {sum(p.numel() for p in SmallNet().parameters())}")
    samples = [MITDataset(args.root, test)[i] for i in range(len(test))]
    results = {
        "R = I, S = 1": evaluate(None, samples),
        "S = intensity, R = I / S": evaluate("flat", samples),
    }
    for use in (False, True):
        name = "reconstruction + priors" if use else "reconstruction only"
        print(f"training: {name}")
        t = time.perf_counter()
        net = train(images, masks, priors, use, args.steps, args.seed)
        results[name] = evaluate(net, samples)
        print(f"  {time.perf_counter() - t:.0f} s")
    print(f"\nMIT LMSE on held-out objects {test} (max side {MAX_SIDE} px), lower is better:")
    for k, v in results.items():
        print(f"  {k:28s} {v:.4f}")


if __name__ == "__main__":
    main()
