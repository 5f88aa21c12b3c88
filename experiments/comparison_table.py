"""The one evaluation table (the training issue, item 5): every system on the three test
families, per factor, with what each was trained for.

    python experiments/comparison_table.py                 # both factors, all families
    python experiments/comparison_table.py --factors 4 --families random
    python experiments/comparison_table.py --only nsrr-fast   # one system again

``--only`` evaluates the named systems and carries every other row over from the
existing ``result.json`` (for a system whose weights have not changed since); the
result then names, per factor, the command that scored each row.

Families (each video from a fresh state; none trained or tuned on):
- ``random``: the randomized scenes' unseen test seeds of ``data/diverse.h5``;
- ``handmade``: the hand-made scenes with varied jitter, test split of the same file;
- ``external``: the independent renderer's clips (Mitsuba 3, ``data/external``, made by
  ``python experiments/external/render_mitsuba.py``), every frame of the three pooled;
- ``game``: the held-out test levels of ``data/game.h5`` (``--preset game``).

Systems: JAU and TUS (nothing to train), the thesis's released model (``--thesis``), the
shipped DLCTUS (``jtus/weights/``: trained on the ``diverse`` data, fine-tuned on the
game and ``diverse`` data half and half, then on both families' static holds), its
second stage (``dlctus-mix``), its first stage alone (``dlctus-diverse``),
that stage fine-tuned on the game data alone (``dlctus-game``) and each
comparison system at its newest training on the ``diverse`` data: the exported weights
of a finished run (``experiments/weights/<model>-x<f>.msgpack``) or, for a run still in
progress, its committed checkpoint (``experiments/checkpoints/<model>-diverse-x<f>/``),
labelled with its epoch; where a fine-tune of the finished run on the game and
``diverse`` data was adopted on the validation splits
(``experiments/weights/<model>-mix-x<f>``, ``common.second_stage``), that instead, its
training budget counting both stages; where a redesign of the system was retrained and
adopted on the validation splits (``common.REDESIGNED``), that. A system with no
training on the ``diverse`` data is listed, not evaluated: its older weights were
trained on other data.

Each cell is PSNR (dB) / SSIM / temporal error (L_st-linear's temporal term, θ=1).
Below the tables, the issue's targets with their measured margins. Writes
``docs/results/comparison-table/result.{md,json}`` and ``readme.md`` (PSNR only, the
README's table; ``--readme-only`` rewrites it from ``result.json``).
"""

from __future__ import annotations

import argparse
import csv
import json
import os

from common import (DLCTUS_RUNS, ROOT, SYSTEMS, THESIS_DIR, command_line, dlctus_run,
                    evaluate_clips, find, redesigned, second_stage,
                    summarize, thesis_path, weights_path, write)

from jtus import evaluate, loading

RESULTS = os.path.join(ROOT, "docs", "results")  # where --only reads the earlier result

FAMILIES = {
    "random": ("randomized scenes, unseen seeds", "data/diverse.h5", "random_*"),
    "handmade": ("hand-made scenes, varied jitter", "data/diverse.h5", "[!r]*"),
    "external": ("independent renderer (Mitsuba 3)", "data/external", None),
    "game": ("held-out game levels (OpenArena)", "data/game.h5", None),
}


def budget(cfg, rows):
    """``{steps, crop, frames, seconds}`` of a run from its config and per-epoch log,
    plus the runs its weights started from (``init_from`` naming exported weights with
    their own ``.json`` and ``-training.csv``): a fine-tune's budget is the whole chain."""
    s = summarize(rows, cfg["epochs"])
    out = {"steps": s["steps"], "crop": cfg["crop"], "frames": cfg["seq_len"],
           "seconds": s["seconds"]}
    init = cfg.get("init_from") or ""
    base = os.path.join(ROOT, init[:-len(".msgpack")]) if init.endswith(".msgpack") else ""
    if base and os.path.exists(base + ".json") and os.path.exists(base + "-training.csv"):
        with open(base + ".json") as fh:
            icfg = json.load(fh)
        with open(base + "-training.csv") as fh:
            before = budget(icfg.get("config", icfg), list(csv.DictReader(fh)))
        out["steps"] += before["steps"]
        out["seconds"] += before["seconds"]
    return out


def systems(factor, thesis_dir=None):
    """``[(label, spec or None, status, budget or None)]`` for every system at ``factor``;
    the thesis's released model as a row when ``thesis_dir`` holds it."""
    out = [("jau", "jau", "-", None), ("tus", "tus", "-", None)]
    if thesis_dir:
        path = thesis_path(factor, thesis_dir)
        out.append(("thesis", f"thesis={path}" if path else None,
                    "released (Sponza, 200 epochs at crop 256)" if path
                    else f"not found under {thesis_dir}", None))
    with open(os.path.join(ROOT, "jtus", "weights", f"dlctus-x{factor}.json")) as fh:
        cfg = json.load(fh)
    with open(os.path.join(ROOT, "jtus", "weights", f"dlctus-x{factor}-training.csv")) as fh:
        rows = list(csv.DictReader(fh))
    out.append(("dlctus", f"dlctus={loading.shipped_path(factor)}",
                "shipped (diverse; game and diverse half and half; both families' static "
                "holds)",
                budget(cfg, rows)))
    for label in DLCTUS_RUNS:
        got = dlctus_run(factor, label)
        if got is None:
            continue
        path, rows, cfg = got
        mix = cfg.get("mix_dataset")
        data = (f"{cfg['data_preset']} and {os.path.basename(mix).removesuffix('.h5')} "
                "half and half" if mix else f"{cfg['data_preset']} preset")
        status = (data + (f", from {cfg['init_from']}" if cfg.get("init_from") else "")
            if path.startswith("experiments/weights/") else
            f"epoch {len(rows)} of {cfg['epochs']} (unfinished)")
        out.append((label, f"{label}={os.path.join(ROOT, path)}", status, budget(cfg, rows)))
    for m in SYSTEMS:
        new = redesigned(m, factor, ROOT)
        if new is not None:  # adopted over the rows below (common.REDESIGNED)
            path, rows, cfg, status = new
            out.append((m, f"{m}={os.path.join(ROOT, path)}", status, budget(cfg, rows)))
            continue
        got = find(m, factor, ROOT)
        if got is None:
            out.append((m, None, "not trained on the diverse data yet", None))
            continue
        rows, planned, src = got
        run_dir = os.path.dirname(src)
        if src.startswith("experiments/weights/"):
            path, status = weights_path(m, factor), "finished"
            cfg_path = os.path.join(ROOT, path.replace(".msgpack", ".json"))
        else:
            path = f"{run_dir}/checkpoint.msgpack"
            status = f"epoch {len(rows)} of {planned} (unfinished)"
            cfg_path = os.path.join(ROOT, run_dir, "config.json")
        with open(cfg_path) as fh:
            cfg = json.load(fh)
        cfg = cfg.get("config", cfg)
        stage = second_stage(m, factor, ROOT) if status == "finished" else None
        if stage is not None:  # adopted on validation: the row is the fine-tune's
            path, rows, cfg = stage
            status = "diverse, then game and diverse half and half"
        out.append((m, f"{m}={os.path.join(ROOT, path)}", status, budget(cfg, rows)))
    return out


def score(entries, family, factor, data_root):
    """``{label: {psnr, ssim, temporal}}`` of the family at ``factor``."""
    _, dataset, pattern = FAMILIES[family]
    if family != "external":
        per_frame, _ = evaluate.evaluate(entries, os.path.join(data_root, dataset), factor,
                                         videos=pattern, progress=False)
        return evaluate.summarize(per_frame)
    return evaluate_clips(entries, factor, os.path.join(data_root, dataset))[1]


def targets(results):
    """The issue's targets as ``(what, margin in dB, met)`` from ``results[f][family]``."""
    out = []

    def psnr(f, fam, lab):
        return results.get(str(f), {}).get(fam, {}).get(lab, {}).get("psnr")

    for f, need in ((4, 2.0), (2, 1.5)):
        for fam in ("random", "handmade"):
            a, b = psnr(f, fam, "dlctus"), psnr(f, fam, "tus")
            if a is not None and b is not None:
                out.append((f"DLCTUS - TUS >= {need} dB, {fam}, {f}x", a - b, a - b >= need))
        a, b = psnr(f, "external", "dlctus"), psnr(f, "external", "tus")
        if a is not None and b is not None:
            out.append((f"DLCTUS - TUS > 0, external, {f}x", a - b, a > b))
        for m in SYSTEMS:
            for fam in FAMILIES:
                a, b = psnr(f, fam, m), psnr(f, fam, "jau")
                if a is not None and b is not None:
                    out.append((f"{m} - JAU > 0, {fam}, {f}x", a - b, a > b))
    for f in (4, 2):
        for fam in FAMILIES:
            for m in ("kpn", "nsrr"):
                a, b = psnr(f, fam, m), psnr(f, fam, "tus")
                if a is not None and b is not None:
                    out.append((f"{m.upper()} - TUS > 0, {fam}, {f}x", a - b, a > b))
            for m in ("dlctus", *DLCTUS_RUNS):
                a, b = psnr(f, fam, m), psnr(f, fam, "thesis")
                if a is not None and b is not None:
                    out.append((f"{m} - thesis > 0, {fam}, {f}x", a - b, a > b))
    return out


def readme_table(results):
    """The README's one table: PSNR (dB) of every system on every family at both
    factors, from ``result.json``."""
    fams = [fam for fam in FAMILIES if any(fam in results.get(f, {}) for f in ("4", "2"))]
    factors = [f for f in ("4", "2") if f in results]
    found = set(lab for f in factors for fam in fams for lab in results[f].get(fam, {}))
    order = ("jau", "tus", "thesis", "dlctus", *DLCTUS_RUNS) + SYSTEMS
    labels = [lab for lab in order if lab in found] + sorted(found - set(order))
    short = {"random": "random scenes", "handmade": "hand-made", "external": "Mitsuba 3",
             "game": "game levels"}
    head = [f"{f}x {short[fam]}" for f in factors for fam in fams]
    lines = ["| system | " + " | ".join(head) + " |", "| --- " * (len(head) + 1) + "|"]
    for lab in labels:
        cells = [results[f].get(fam, {}).get(lab) for f in factors for fam in fams]
        lines.append(f"| {lab} | " + " | ".join(f"{c['psnr']:.2f}" if c else "-"
                                                  for c in cells) + " |")
    return "\n".join(lines)


def write_readme_table(name, results=None):
    """``docs/results/<name>/readme.md`` from ``results`` (default: that folder's
    ``result.json``)."""
    d = os.path.join(RESULTS, name)
    if results is None:
        with open(os.path.join(d, "result.json")) as fh:
            results = json.load(fh)
    table = readme_table(results)
    os.makedirs(d, exist_ok=True)
    with open(os.path.join(d, "readme.md"), "w") as fh:
        fh.write(table + "\n")
    return table


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=(2, 4))
    p.add_argument("--families", nargs="+", default=list(FAMILIES), choices=list(FAMILIES))
    p.add_argument("--data-root", default=ROOT,
                   help="folder holding data/diverse.h5 and data/external/")
    p.add_argument("--name", default="comparison-table")
    p.add_argument("--only", nargs="+", metavar="SYSTEM",
                   help="evaluate only these systems; the other rows come from the existing "
                        "result.json")
    p.add_argument("--thesis", default=THESIS_DIR,
                   help="folder of the thesis's released checkpoints (a row when present; "
                        "'' for none)")
    p.add_argument("--readme-only", action="store_true",
                   help="only rewrite readme.md (the README's table) from result.json")
    args = p.parse_args(argv)
    if args.readme_only:
        print(write_readme_table(args.name))
        return
    old = {}
    if args.only:
        path = os.path.join(RESULTS, args.name, "result.json")
        if not os.path.exists(path):
            p.error(f"--only: {path} is missing; run without --only first")
        with open(path) as fh:
            old = json.load(fh)
        if sorted(map(str, args.factors)) != sorted(k for k in old if k.isdigit()) or any(
                fam not in old[str(f)] for f in args.factors for fam in args.families):
            p.error(f"--only: {path} holds other factors or families than asked for")
    for fam in args.families:  # every input checked before the first evaluation
        path = os.path.join(args.data_root, FAMILIES[fam][1])
        if not os.path.exists(path):
            p.error(f"--families {fam}: {path} is missing (see this script's docstring)")
    results, lines, command = {}, [], command_line()
    for f in args.factors:
        rows = systems(f, args.thesis)
        if args.only:
            unknown = set(args.only) - {lab for lab, spec, _, _ in rows if spec}
            if unknown:
                p.error(f"--only: no weights to evaluate for {sorted(unknown)} at {f}x")
        todo = [spec for lab, spec, _, _ in rows if spec and (not args.only or lab in args.only)]
        entries = loading.load_all(todo, f)
        res = results[str(f)] = {fam: score(entries, fam, f, args.data_root)
                                 for fam in args.families}
        made = res["made_by"] = {e.label: command for e in entries}
        for lab, spec, _, _ in rows:
            if spec and lab not in made:  # carried over (--only)
                for fam in args.families:
                    res[fam][lab] = old[str(f)][fam][lab]
                made[lab] = old[str(f)]["made_by"][lab]
        lines += [f"**{f}x** (each cell: PSNR dB / SSIM / temporal error)", "",
                  "| system | weights | " + " | ".join(FAMILIES[fam][0] for fam in args.families)
                  + " | Adam steps | crop | frames | training wall time |",
                  "| --- | --- | " + "--- | " * len(args.families) + "--- | --- | --- | --- |"]
        for lab, spec, status, b in rows:
            cells = []
            for fam in args.families:
                s = res[fam].get(lab)
                cells.append(f"{s['psnr']:.2f} / {s['ssim']:.4f} / {s['temporal']:.5f}"
                              if s else "-")
            bud = (f"{b['steps']:,} | {b['crop']} | {b['frames']} | {b['seconds'] / 3600:.1f} h"
                   if b else "- | - | - | -")
            lines.append(f"| {lab} | {status} | " + " | ".join(cells) + f" | {bud} |")
            if b:
                results[str(f)].setdefault("budget", {})[lab] = dict(b, status=status)
        lines.append("")
    tg = targets(results)
    lines += ["Targets (PSNR margins):", "", "| target | margin (dB) | met |",
              "| --- | --- | --- |"]
    lines += [f"| {what} | {m:+.2f} | {'yes' if ok else '**no**'} |" for what, m, ok in tg]
    results["targets"] = [{"target": w, "margin_db": m, "met": bool(ok)} for w, m, ok in tg]
    results["command"] = command
    note = ("Training wall time: the sum of the per-epoch times of the run's log, on one "
            "core of a 2-core machine often shared with other work (docs/comparison.md).")
    carried = {(f, lab): c for f in args.factors
               for lab, c in results[str(f)]["made_by"].items() if c != command}
    if carried:
        note += "\n\nRows carried over from earlier runs (`--only`): " + "; ".join(
            f"{f}x {lab}: `{c}`" for (f, lab), c in sorted(carried.items())) + "."
    write(args.name, "\n".join(lines), results, note=note)
    write_readme_table(args.name, results)


if __name__ == "__main__":
    main()
