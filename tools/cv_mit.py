"""Cross-validate parameter choices on the MIT-Berkeley objects (k-fold and leave-one-out).

A configuration is a preset (``--preset``), fixed changes over it (``--changes``, a JSON object;
``--variant`` sets an ablation variant's switches) and a grid of candidate values
(``--grid``, a JSON object of lists, or ``@file.json``). On the training objects of each fold
the values are chosen by a coordinate search (each grid parameter in turn keeps the candidate
with the lowest mean training LMSE, ``--passes`` passes; :func:`torchiid.eval.crossval.
coordinate_search`), then scored on the fold's validation objects. With no grid the
configuration is scored as given, and then the mean validation LMSE equals the mean over all
objects: only the spread is news. Folds are fixed: with the object names sorted, fold ``j``
holds names ``j, j + k, …`` (for the shared ten: apple+panther, box+paper1, cup1+phone,
dinosaur+squirrel, frog1+teabag2).

    python tools/cv_mit.py ../shared/data/mit-berkeley --cache cv-cache
    python tools/cv_mit.py ../shared/data/mit-berkeley --preset paper --cache cv-cache
    python tools/cv_mit.py ../shared/data/mit-berkeley --cache cv-cache \\
        --grid '{"lambda_s": [0, 0.005, 0.01, 0.02], "t_e": [0, 0.0075, 0.015, 0.03]}'
    python tools/cv_mit.py ../shared/data/mit-berkeley --cache cv-cache --revert
    python tools/cv_mit.py ../shared/data/mit-berkeley --cache cv-cache --revert lambda_s=0
    python tools/cv_mit.py ../shared/data/mit-berkeley --cache cv-cache --passes 1 --nested \\
        --grid '{"lambda_m": [0.02, 0.01], "lambda_s": [0, 0.01], "t_e": [0.015, 0], ...}'

``--revert`` tests the preset's values that differ from the paper's (the ``paper`` preset's
energy, and ``dark_level``/``clip_level``, which the paper does not have), each alone, all
together, and the solver caps apart (they do not count): A is the preset as given, B the
value(s) set back to the paper's, and each fold chooses between them on its training objects.
Rules: revert when ``B − A <= sd`` (standard deviation over the k folds of A's validation
LMSE), ``<= se = sd / √k``, or ``<= se(B − A)`` (paired: the standard error over folds of the
fold's mean difference, blind to how much harder some objects are); objects made worse too.

``--nested`` cross-validates the whole tuning rule (:mod:`torchiid.eval.selection`): on each
fold's training objects the grid is fitted, then every fitted value goes back to the paper's
(:func:`references`) unless that worsens the training LMSE by more than ``se(B − A)`` over an
inner split of those objects; what is left is scored on the fold's validation objects.

Every ``(parameters, object)`` LMSE is computed once: the JSON-lines cache in ``--cache`` is
keyed by the parameters (:func:`key_params`), the object, the input file, a fingerprint of its
files, torch's thread count and the code version (a hash of the ``torchiid`` sources and the
torch version), so k-fold, leave-one-out, the fit on all objects and later runs share
decompositions. Stage 0 features are computed once per object and feature-relevant parameter
set within a run. Scores are the in-memory MIT LMSE (``torchiid eval mit`` gives the same
figures from the files a user gets). MIT-Berkeley-Natural inputs (``--natural DIR``: one
folder per object with ``diffuse.png``; ground truth from the same folder, else from ROOT's)
are cross-validated the same way.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import torch

import torchiid
import torchiid.params
from torchiid.core.exceptions import TorchiidError
from torchiid.eval import score_sample
from torchiid.eval.crossval import (
    JsonlCache,
    coordinate_search,
    cross_validate,
    format_folds,
    format_table,
    kfold_splits,
    memoised,
    reversion_test,
)
from torchiid.eval.datasets import DenseSample
from torchiid.eval.selection import format_nested, nested_cross_validate
from torchiid.io import load_image, load_mask
from torchiid.model import decompose
from torchiid.params import ADDED_SINCE, Parameters

#: the parameters Stage 0 reads (with which of its features the active priors need)
FEATURE_FIELDS = (
    "patch_size",
    "patch_stride",
    "feature_mode",
    "feature_backend",
    "lle_features",
    "seed",
    "segment_scale",
    "proposal_pca_dim",
    "max_side",
)
#: solver tolerances and caps: reported apart, not counted as tuned values
SOLVER_FIELDS = (
    "cg_tol",
    "cg_max_iter",
    "warm_cg_max_iter",
    "coarse_levels",
    "shading_preconditioner",
    "bregman_iter",
    "bregman_cg_iter",
    "bregman_tol",
    "bregman_gap_tol",
    "bregman_theta_floor",
    "bregman_cg_tol",
    "bregman_warm_state",
    "converge",
)
#: additions the paper does not have, with the value that turns them off
PAPER_OFF = {"dark_level": 0.0, "clip_level": 0.0}
#: sources that measure but take no part in a decomposition or its MIT score
NOT_SCORED = (
    "torchiid/eval/crossval.py",
    "torchiid/eval/selection.py",
    "torchiid/eval/texture.py",
    "torchiid/synthetic_texture.py",
)
NATURAL_ABSENT = (
    "MIT-Berkeley-Natural inputs: absent (the shared data has only laboratory lighting: "
    "diffuse.png, original.png, light01..10.png; pass --natural DIR where the data has them)"
)


def code_version() -> str:
    """Hash of the torchiid sources (but :data:`NOT_SCORED`), model manifest and torch version."""
    pkg = Path(torchiid.__file__).parent
    h = hashlib.sha256(torch.__version__.encode())
    files = sorted(pkg.rglob("*.py")) + [pkg.parent / "models" / "manifest.json"]
    for f in files:
        rel = f.relative_to(pkg.parent).as_posix()
        if f.is_file() and rel not in NOT_SCORED:
            h.update(rel.encode() + b"\0" + f.read_bytes())
    return f"{torchiid.__version__}+{h.hexdigest()[:16]}"


def key_params(p: Parameters) -> dict[str, Any]:
    """The parameters of a cache key: all, but those at the value that turns an addition off.

    A parameter added to the method (off by default, :data:`torchiid.params.ADDED_SINCE`)
    then leaves the keys of every result computed without it unchanged.
    """
    off = {k: v for added in ADDED_SINCE.values() for k, v in added.items()}
    return {k: v for k, v in p.to_dict().items() if not (k in off and off[k] == v)}


def _image(path: Path) -> torch.Tensor:
    return load_image(path, linear=True, alpha="error", min_side=1).image


def load_objects(root: Path, input_name: str, gt_root: Path | None = None, names=None) -> dict:
    """``{object: (DenseSample, fingerprint)}`` for every folder of ``root`` with the input.

    Ground truth (reflectance, shading, mask) is read from the object's folder, else from the
    same object's folder in ``gt_root``.
    """
    out = {}
    for d in sorted(p for p in root.iterdir() if (p / f"{input_name}.png").is_file()):
        if names and d.name not in names:
            continue
        files = {"input": d / f"{input_name}.png"}
        for part in ("reflectance", "shading", "mask"):
            here = [d / f"{part}.png"] + ([gt_root / d.name / f"{part}.png"] if gt_root else [])
            found = next((p for p in here if p.is_file()), None)
            if found is None:
                raise SystemExit(f"{d}: no {part}.png here or in the laboratory folder")
            files[part] = found
        digest = hashlib.sha256()
        for f in files.values():
            digest.update(f.read_bytes())
        sample = DenseSample(
            d.name,
            _image(files["input"]),
            _image(files["reflectance"]),
            _image(files["shading"]).mean(0, keepdim=True),
            load_mask(files["mask"]),
        )
        out[d.name] = (sample, digest.hexdigest()[:16])
    if names and set(names) - set(out):
        raise SystemExit(f"{root}: no objects {sorted(set(names) - set(out))}")
    if len(out) < 2:
        raise SystemExit(f"{root}: fewer than two object folders with {input_name}.png")
    return out


class MITScore:
    """``score(changes, object)``: the MIT LMSE of the base parameters with ``changes``."""

    def __init__(self, objects: dict, base: Parameters, cache: JsonlCache, tag: str, code: str):
        self.objects, self.base, self.cache, self.tag, self.code = objects, base, cache, tag, code
        self.features: dict[tuple, Any] = {}
        self.computed = self.reused = 0

    def params(self, changes: dict[str, Any]) -> Parameters:
        """The base parameters with ``changes``."""
        return self.base.replace(**changes)

    def _features(self, name: str, p: Parameters):
        flat = p.to_dict()
        key = (name, *(flat[f] for f in FEATURE_FIELDS))
        have = self.features.get(key)
        if have is None:
            return key, None
        sw, rw = p.shading.weights(), p.reflectance.weights()
        needs = {
            "patch_features": sw["S_c"] > 0,
            "similarity": sw["S_m"] > 0,
            "gpca": rw["B"] > 0,
            "segments": rw["C"] > 0,
        }
        if any(need and getattr(have, f) is None for f, need in needs.items()):
            return key, None
        return key, have

    def __call__(self, changes: dict[str, Any], name: str) -> float:
        sample, fingerprint = self.objects[name]
        p = self.params(changes)
        key = self.cache.key(
            params=key_params(p),
            object=name,
            input=self.tag,
            data=fingerprint,
            code=self.code,
            threads=torch.get_num_threads(),  # the solvers' sums depend on it, a little
        )
        rec = self.cache.get(key)
        if rec is not None:
            self.reused += 1
            return rec["lmse"]
        fkey, feats = self._features(name, p)
        t0 = time.perf_counter()
        out = decompose(
            sample.image[None],
            p,
            mask=sample.mask[None],
            features=feats,
            return_features=feats is None,
            return_stage1=False,
        )
        seconds = time.perf_counter() - t0
        if feats is None:  # keep what this and an earlier run computed
            new, old = out.features, self.features.get(fkey)
            kept = {f.name: getattr(old, f.name, None) for f in fields(new)}
            self.features[fkey] = replace(
                new, **{n: v for n, v in kept.items() if v is not None and getattr(new, n) is None}
            )
        scores = score_sample("mit", sample, out.reflectance, out.shading)
        base = self.base.to_dict()
        changed = {k: v for k, v in p.to_dict().items() if v != base[k]}
        record = {"object": name, "input": self.tag, "data": fingerprint, "code": self.code}
        record["changes"] = changed
        record.update(scores, seconds=round(seconds, 2), params=p.to_dict())
        self.cache.put(key, record)
        self.computed += 1
        print(
            f"  {name:<10} {json.dumps(changed)[:70]:<70} {scores['lmse']:.5f} {seconds:5.1f} s",
            file=sys.stderr,
            flush=True,
        )
        return scores["lmse"]


def _value(text: str) -> Any:
    try:
        return json.loads(text)
    except ValueError:
        return text


def revert_list(preset: str, given: list[str] | None) -> tuple[dict, dict]:
    """``(energy, solver)``: the preset's values that differ from the paper's, as paper values."""
    if given:
        pairs = dict(item.split("=", 1) for item in given)
        chosen = {k: _value(v) for k, v in pairs.items()}
    else:
        mine, paper = Parameters.preset(preset).to_dict(), Parameters.preset("paper").to_dict()
        chosen = {k: v for k, v in paper.items() if mine[k] != v}
        chosen.update({k: v for k, v in PAPER_OFF.items() if mine[k] != v})
    Parameters().replace(**chosen)  # unknown names and bad values fail here, by name
    energy = {k: v for k, v in chosen.items() if k not in SOLVER_FIELDS}
    solver = {k: v for k, v in chosen.items() if k in SOLVER_FIELDS}
    return energy, solver


def references(names) -> dict[str, Any]:
    """The value each named parameter goes back to: the paper's, or the one that turns it off."""
    paper = Parameters.preset("paper").to_dict()
    return {n: PAPER_OFF.get(n, paper[n]) for n in names}


def nested(score, names: list[str], grid: dict, start: dict, args, title: str) -> dict:
    """Print (and return) the nested cross-validation of fitting ``grid`` and sending back."""
    out = {}
    ref = references(grid)
    for k in sorted({args.folds} | (set() if args.no_loo else {len(names)})):
        res = nested_cross_validate(score, names, grid, ref, k, start=start, passes=args.passes)
        split = "leave-one-out" if k == len(names) else f"{k}-fold"
        print(format_nested(res, f"## {title}: fit, then send back, {split}"), "\n", flush=True)
        per = ", ".join(f"{n} {v:.5f}" for n, v in res.cv.sample_scores.items())
        print(f"validation LMSE per object: {per}\n", flush=True)
        out[f"nested_{split}"] = {
            **_cv_json(res.cv),
            "selections": [vars(s) for s in res.selections],
            "inner_k": res.inner_k,
            "reference": ref,
        }
    return out


def revert_tests(base: Parameters, energy: dict, solver: dict) -> dict[str, dict]:
    """Labelled changes: each value alone, then all energy values, then all caps together."""
    tests = {n: {n: v} for n, v in energy.items()}
    if len(energy) > 1:
        tests["all of the above"] = dict(energy)
    tests.update({f"{n} (cap)": {n: v} for n, v in solver.items()})
    if len(solver) > 1:
        tests["all caps"] = dict(solver)
    return tests


#: columns of the reversion table
REVERT_HEADER = (
    "value|A's|B's|A: as given|B: changed|B − A|sd(A)|se(A)|se(B − A)|objects worse|"
    "fold choice|choice: validation|sd rule|se rule|paired rule"
).split("|")


def revert_table(rows, base: Parameters, n: int) -> str:
    """The reversion test's rows as a table."""
    out = []
    for r in rows:
        tuned = ", ".join(str(base.to_dict()[k]) for k in r.changes)
        paper = ", ".join(str(v) for v in r.changes.values())
        picks = " ".join("P" if p else "T" for p in r.picks_b)
        rules = ["revert" if r.reverts(k) else "keep" for k in ("sd", "se", "paired")]
        figures = [r.score_a, r.score_b, r.delta, r.sd, r.se, r.se_paired]
        out.append([r.name, tuned, paper, *figures, f"{r.worse}/{n}", picks])
        out[-1] += [r.choice_validation, *rules]
    return format_table(REVERT_HEADER, out)


def analyse(score, names: list[str], grid: dict, start: dict, args, title: str) -> dict:
    """Print k-fold, leave-one-out, the fit on all objects and the per-object table."""
    report: dict[str, Any] = {"title": title, "objects": names}
    kf = cross_validate(score, names, grid, args.folds, start, args.passes)
    print(format_folds(kf, f"## {title}: {args.folds}-fold"), "\n", flush=True)
    report["kfold"] = _cv_json(kf)
    loo = None
    if not args.no_loo:
        loo = cross_validate(score, names, grid, len(names), start, args.passes)
        print(format_folds(loo, f"## {title}: leave-one-out"), "\n", flush=True)
        report["loo"] = _cv_json(loo)
    fit = coordinate_search(score, names, grid, start, args.passes) if grid else None
    if fit is not None:
        print(
            f"fit on all {len(names)} objects: {json.dumps(fit.changes)}, training LMSE "
            f"{fit.score:.5f} (the tuning as usually done; compare the validation means)\n"
        )
        report["fit_all"] = {"changes": fit.changes, "train": fit.score}
    rows = []
    chosen = fit.changes if fit else {}
    for n in names:
        row = [n, score({}, n), score(chosen, n), kf.sample_scores[n]]
        if loo is not None:
            ch = loo.sample_changes[n]
            row += [loo.sample_scores[n], ", ".join(f"{k}={ch[k]}" for k in grid if k in ch)]
        rows.append(row)
    mean = lambda i: sum(r[i] for r in rows) / len(rows)  # noqa: E731
    rows.append(["**mean**", mean(1), mean(2), mean(3)] + ([mean(4), ""] if loo else []))
    header = ["object", "as given", "fit on all (train)", f"{args.folds}-fold validation"]
    header += ["LOO validation", "LOO chosen"] if loo else []
    print(format_table(header, rows), "\n", flush=True)
    report["per_object"] = {r[0]: r[1:] for r in rows}
    return report


def _cv_json(cv) -> dict:
    names = ("mean_validation", "sd_validation", "se_validation", "mean_train", "gap")
    return {**{n: getattr(cv, n) for n in names}, "folds": [vars(f) for f in cv.folds]}


def _json_arg(text: str, what: str) -> Any:
    if text.startswith("@"):
        text = Path(text[1:]).read_text(encoding="utf-8")
    try:
        return json.loads(text)
    except ValueError as exc:
        raise SystemExit(f"{what}: not valid JSON ({exc})") from None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", type=Path, help="the MIT-Berkeley folder (one folder per object)")
    ap.add_argument("--preset", default="default", help="the preset (default: default)")
    ap.add_argument("--changes", default="{}", help="JSON object of fixed changes")
    ap.add_argument("--variant", help="an ablation variant (v1..v7, baseline1..3)")
    ap.add_argument("--grid", default="{}", help="JSON object of candidate lists (or @file)")
    ap.add_argument("--passes", type=int, default=2, help="coordinate-search passes (2)")
    ap.add_argument("--folds", type=int, default=5, help="k of the k-fold split (5)")
    ap.add_argument("--no-loo", action="store_true", help="skip leave-one-out")
    ap.add_argument(
        "--revert",
        nargs="*",
        metavar="NAME=VALUE",
        help="reversion test of the tuned values (none given: all that differ)",
    )
    ap.add_argument(
        "--nested",
        action="store_true",
        help="cross-validate fitting the grid and then sending back to the paper's values "
        "what does not earn its place (instead of the plain refit)",
    )
    ap.add_argument("--input", default="diffuse", choices=("diffuse", "original"))
    ap.add_argument("--objects", help="comma-separated object names (default: all)")
    ap.add_argument("--natural", type=Path, help="MIT-Berkeley-Natural folder")
    ap.add_argument("--cache", type=Path, help="folder of the JSON-lines score cache")
    ap.add_argument("--json", type=Path, help="also write the results here as JSON")
    ap.add_argument(
        "--code-version",
        help="use this code version for the cache keys (one printed by an earlier run, where "
        "only sources that take no part in a decomposition have changed since)",
    )
    args = ap.parse_args()
    try:
        base = Parameters.preset(args.preset).replace(**_json_arg(args.changes, "--changes"))
        if args.variant:
            base = base.variant(args.variant)
        grid = _json_arg(args.grid, "--grid")
        if not isinstance(grid, dict):
            raise SystemExit("--grid: expected a JSON object of lists")
        if args.nested and not grid:
            raise SystemExit("--nested needs a --grid of the values to fit")
        for name, values in grid.items():
            if not isinstance(values, list) or not values:
                raise SystemExit(f"--grid: {name} must have a non-empty list of values")
            for v in values:
                base.replace(**{name: v})  # every candidate must be a valid value
        energy, solver = {}, {}
        if args.revert is not None:
            energy, solver = revert_list(args.preset, args.revert)
    except TorchiidError as exc:
        raise SystemExit(f"error: {exc}") from None
    names = args.objects.split(",") if args.objects else None
    code = args.code_version or code_version()
    cache = JsonlCache(args.cache)
    print(
        f"# cross-validation on MIT-Berkeley ({args.root}), preset {args.preset}"
        f"{', variant ' + args.variant if args.variant else ''}, changes {args.changes}, "
        f"grid {json.dumps(grid)}, {args.passes} passes; code {code}; cache "
        f"{args.cache or '(memory)'} ({len(cache)} records); OMP_NUM_THREADS="
        f"{os.environ.get('OMP_NUM_THREADS', 'unset')}\n"
    )
    sets = [(f"laboratory light ({args.input}.png)", args.root, args.input, None)]
    natural = args.natural
    if natural is None:
        near = [p for p in args.root.parent.iterdir() if p.is_dir() and "natural" in p.name.lower()]
        natural = near[0] if near else None
    if natural is None:
        print(NATURAL_ABSENT + "\n")
    else:
        sets.append((f"natural light ({natural})", natural, "diffuse", args.root))
    report = {"preset": args.preset, "grid": grid, "code": code, "sets": []}
    for title, root, input_name, gt_root in sets:
        objects = load_objects(root, input_name, gt_root, names)
        if not 2 <= args.folds <= len(objects) or args.passes < 1:
            raise SystemExit(f"--folds must be 2..{len(objects)} and --passes >= 1")
        tag = f"{root.resolve()}:{input_name}"
        score = MITScore(objects, base, cache, tag, code)
        memo = memoised(score)
        folds = kfold_splits(list(objects), args.folds)
        print(f"folds: {'; '.join(' '.join(v) for _, v in folds)}\n")
        start = {n: base.to_dict()[n] for n in grid}
        if args.nested:
            rep = {"title": title, "objects": list(objects)}
            rep.update(nested(memo, list(objects), grid, start, args, title))
        else:
            rep = analyse(memo, list(objects), grid, start, args, title)
        if energy or solver:
            tests = revert_tests(base, energy, solver)
            what = "values given" if args.revert else "back to the paper's values"
            for k in sorted({args.folds, len(objects)}):
                rows = reversion_test(memo, list(objects), tests, k)
                split = "leave-one-out" if k == len(objects) else f"{k}-fold"
                print(
                    f"## {title}: {what}, {split} (A: {args.preset} as given, B: the value(s) "
                    f"changed; fold choice: P where the fold's training objects pick B; "
                    f"rules: take B when B − A <= sd(A), "
                    f"se(A) or se(B − A))\n\n{revert_table(rows, base, len(objects))}\n",
                    flush=True,
                )
                rep[f"revert_{split}"] = [{**vars(r), "delta": r.delta} for r in rows]
        print(f"decompositions: {score.computed} computed, {score.reused} from the cache\n")
        report["sets"].append(rep)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=str) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
