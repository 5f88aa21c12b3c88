"""Shared pieces of the experiment scripts: output folders, hardware, tables."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import shlex
import shutil
import sys
import time


import numpy as np

from jtus import evaluate, recipe, timing, train

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "docs", "results")

# the DLCTUS reprojection warps the experiments compare: (method, Keys a), cheapest first
WARPS = (("bilinear", -0.75), ("bicubic5", -0.75), ("bicubic9", -0.75), ("catmull_rom", -0.5),
         ("bicubic", -0.75))


def cpu_per_wall(fn, repeats):
    """``(wall seconds per call, process CPU seconds per wall second)`` over ``repeats``
    calls of ``fn`` after one warm-up call (its compile not counted)."""
    fn()
    c0, t0 = os.times(), time.perf_counter()
    for _ in range(repeats):
        fn()
    c1, t1 = os.times(), time.perf_counter()
    return (t1 - t0) / repeats, (c1.user - c0.user + c1.system - c0.system) / (t1 - t0)


def rounds_ms(fns, repeats, rounds):
    """``{name: [ms per call in each round]}``: ``rounds`` rounds of
    ``timing.timeit_round_robin(fns, repeats)``, every function timed in turn within each."""
    times = {k: [] for k in fns}
    for _ in range(rounds):
        for k, v in timing.timeit_round_robin(fns, repeats).items():
            times[k].append(v * 1e3)
    return times


def out_dir(name):
    d = os.path.join(RESULTS, name)
    os.makedirs(d, exist_ok=True)
    return d


def hardware_line():
    return timing.hardware_line()


def command_line():
    return "python " + shlex.join([os.path.relpath(sys.argv[0], ROOT)] + sys.argv[1:])


def write(name, table, data, note=""):
    """``docs/results/<name>/result.md`` (table, command, hardware) and ``result.json``."""
    d = out_dir(name)
    with open(os.path.join(d, "result.md"), "w") as fh:
        fh.write(f"{table}\n\nCommand: `{command_line()}`  \nHardware: {hardware_line()}.\n")
        if note:
            fh.write(f"\n{note}\n")
    with open(os.path.join(d, "result.json"), "w") as fh:
        json.dump(data, fh, indent=1, default=float)
    print(table)
    return d


def weights_path(name, factor):
    """Where a trained comparison system's parameters are shipped, relative to ``ROOT``:
    ``experiments/weights/<name>-x<factor>.msgpack`` (its ``.json`` config and
    ``-training.csv`` log beside it)."""
    return f"experiments/weights/{name}-x{factor}.msgpack"


def l1_recipe(factor, epochs, dataset, steps_per_epoch=100, seed=0):
    """The short DLCTUS recipe of the θ sweep (``sweep_theta.py``): the ``default``
    preset with one validation video. Returns ``(config, workdir of the L1 run)``."""
    import dataclasses

    from jtus.config import PRESETS

    config = dataclasses.replace(PRESETS["default"], factor=factor, epochs=epochs,
                                 steps_per_epoch=steps_per_epoch, seed=seed, dataset=dataset,
                                 val_videos=1)
    return config, os.path.join(ROOT, "runs", "sweep_theta", "L1")


# ---------------------------------------------------------------- runs kept across sessions
# A run's files (checkpoint, config, per-epoch log; about 1 MB) copied from ``runs/`` to
# ``experiments/checkpoints/`` to be committed while it trains, and back into a fresh
# machine's ``runs/`` to be resumed (``saved_runs.py``, ``ablations.py``,
# ``train_comparison.sh``); a finished run leaves git and keeps its exported weights.

SAVED = ("checkpoint.msgpack", "config.json", "metrics.json", "metrics.csv")


def copy_run(src, dst):
    """Copy a run's files (those of ``SAVED`` that exist) from ``src`` to ``dst``; True
    if it had a checkpoint, False (and nothing copied) if not."""
    if not os.path.exists(os.path.join(src, SAVED[0])):
        return False
    os.makedirs(dst, exist_ok=True)
    for name in SAVED:
        if os.path.exists(os.path.join(src, name)):
            shutil.copy2(os.path.join(src, name), os.path.join(dst, name))
    return True


# ---------------------------------------------------------------- ablation studies

LR = 3e-4  # the ablations' learning rate (docstring)


def study_name(study, lr=LR):
    """``ablation-<study>``, with ``-lr<lr>`` at another learning rate than ``LR``: the
    folder of a study's runs (under ``runs/`` and ``experiments/checkpoints/``) and of
    its results (under ``docs/results/``)."""
    return f"ablation-{study}" if lr == LR else f"ablation-{study}-lr{lr:g}"


def variants(study, thetas):
    """``[(label, Config changes)]`` of a study."""
    if study == "accumulation":
        return [("with buffer", {}),
                ("without buffer", {"model_overrides": (("accumulation", False),)})]
    if study == "warp":
        return [("bicubic (16 taps, a=-0.75)", {"model_overrides": (("warp", "bicubic"),)}),
                ("bilinear", {"model_overrides": (("warp", "bilinear"),)})]
    if study == "theta":
        return [("L1", {"loss": "l1"})] + [(f"L_st-linear θ={t}", {"loss": "st-linear",
                                                                   "theta": t}) for t in thetas]
    raise ValueError(f"study: expected accumulation, warp or theta, got {study!r}")


STUDIES = ("accumulation", "warp", "theta")


def what_trains(cfg):
    """A run's training with its model overrides resolved: two variants that set model
    fields to values that are already the defaults train the same network."""
    return dataclasses.replace(cfg, model_overrides=()), recipe.model_for(cfg).config


def run_of(study, label, changes, base, seed, thetas=()):
    """``(workdir, config)`` of a variant's run: those of the first variant (studies in
    ``STUDIES`` order) that trains the same network with the same seed. DLCTUS as the
    recipe has it is the "with buffer", the "bicubic" and the "L1" variant: it trains
    once, in ``runs/ablation-accumulation/``, with the "with buffer" config (which a
    resumed run must match exactly), and the warp and θ studies read that run."""
    key = what_trains(dataclasses.replace(base, seed=seed, **changes))
    for s in STUDIES[:STUDIES.index(study) + 1]:
        for lab, ch in variants(s, thetas):
            cfg = dataclasses.replace(base, seed=seed, **ch)
            if (s, lab) == (study, label) or what_trains(cfg) == key:
                return (os.path.join(ROOT, "runs", study_name(s, base.lr),
                                     f"{slug(lab)}-s{seed}"), cfg)
    raise ValueError(f"label: {label!r} is not a variant of the {study} study")


def slug(label):
    return "".join(c if c.isalnum() else "_" for c in label).strip("_").lower()


def saved_dir(work):
    """Where a run's checkpoint is kept between sessions (committed)."""
    study, run = os.path.split(os.path.relpath(work, os.path.join(ROOT, "runs")))
    return os.path.join(ROOT, "experiments", "checkpoints", study, run)


def save_runs(study, lr=LR):
    """Copy every run of ``study`` that has a checkpoint to its saved directory."""
    root = os.path.join(ROOT, "runs", study_name(study, lr))
    for run in sorted(os.listdir(root)) if os.path.isdir(root) else []:
        work = os.path.join(root, run)
        if copy_run(work, saved_dir(work)):
            print(f"saved {os.path.relpath(work, ROOT)} -> "
                  f"{os.path.relpath(saved_dir(work), ROOT)}")


def runs_so_far(study, lr=LR):
    """Markdown lines on a study's runs before its results exist: each committed run's
    epochs, last validation PSNR and whether it collapsed (``train.collapsed``)."""
    name = study_name(study, lr)
    root = os.path.join(ROOT, "experiments", "checkpoints", name)
    runs = sorted(os.listdir(root)) if os.path.isdir(root) else []
    if not runs:
        return []
    rows = []
    for run in runs:
        with open(os.path.join(root, run, "config.json")) as fh:
            epochs = json.load(fh)["epochs"]
        with open(os.path.join(root, run, "metrics.json")) as fh:  # the history train resumes
            hist = json.load(fh)
        why = train.collapsed(hist)
        done = len(hist) >= epochs
        status = f"collapsed ({why})" if why else "trained" if done else "in training"
        psnr = f"{hist[-1]['val_psnr']:.2f}" if hist else "-"
        rows.append(f"| {run} | {len(hist)} of {epochs} | {psnr} | {status} |")
    shared = "" if study == "accumulation" else (
        " The first variant trains the same network as the accumulation study's \"with "
        "buffer\" runs and reads those (`run_of`).")
    lr_arg = "" if lr == LR else f" --lr {lr:g}"
    return [f"In progress: the runs so far (committed in "
            f"`experiments/checkpoints/{name}/`; `python experiments/ablations.py "
            f"--study {study}{lr_arg}` resumes them and writes the table when all are done)."
            f"{shared}",
            "", "| run | epochs | last validation PSNR (dB) | status |",
            "| --- | --- | --- | --- |", *rows]


# ---------------------------------------------------------------- comparison runs

SYSTEMS = ("mlp", "kpn", "nsrr-fast", "nsrr")
FACTORS = (4, 2)

# the thesis's released checkpoints (for comparison only: never shipped, never trained
# on), as its README names them, under a folder like ../shared/thesis
THESIS = {4: os.path.join("MasterNet4x4", "modelMaster.pt"),
          2: os.path.join("MasterNet2x2", "modelMaster_best.pt")}
THESIS_DIR = os.path.join(ROOT, "..", "shared", "thesis")


def thesis_path(factor, thesis_dir=THESIS_DIR):
    """The thesis's released checkpoint at ``factor`` under ``thesis_dir``, or None."""
    path = os.path.join(thesis_dir, THESIS[factor]) if thesis_dir else ""
    return path if path and os.path.exists(path) else None


def second_stage(model, factor, root=ROOT):
    """``(path, rows, config)`` of a comparison system's adopted second stage at
    ``factor``: its ``diverse`` weights fine-tuned with the ``game-mix`` preset and
    chosen on the validation splits (``docs/comparison.md``), exported as
    ``experiments/weights/<model>-mix-x<f>`` (``.msgpack``, ``.json`` whose
    ``init_from`` names the first stage, ``-training.csv``); None where none was
    adopted."""
    return _exported(root, f"{model}-mix", factor)


# comparison systems whose design was changed and retrained, each adopted on the
# validation splits over its earlier rows (docs/comparison.md), at the factors where
# it was: model -> {factor: (exported weights' base name under experiments/weights/,
# the table's description of them)}
def _at_both(name, description):
    return {f: (name, description) for f in FACTORS}


_NSRR = "exposure-normalized colour; diverse, then fine-tunes on game and diverse half and half"
REDESIGNED = {"mlp": _at_both("mlp-jau-logmse", "JAU base, contrast-normalized patches; both "
                                                "families' holds, then log-MSE on game and "
                                                "diverse half and half"),
              "kpn": _at_both("kpn-clamp", "the current kernel mixes the samples themselves, "
                                           "the history clamped to their box; diverse, then "
                                           "fine-tunes"),
              "nsrr-fast": _at_both("nsrr-fast-exposure", _NSRR),
              "nsrr": {4: ("nsrr-exposure", _NSRR),
                       2: ("nsrr-exposure", _NSRR + ", the last round with log-MSE")}}


def redesigned(model, factor, root=ROOT):
    """``(path, rows, config, description)`` of a comparison system's adopted redesign at
    ``factor`` (``REDESIGNED``: ``experiments/weights/<name>-x<f>`` with its config and
    per-epoch log), or None where it has none."""
    if factor not in REDESIGNED.get(model, {}):
        return None
    name, description = REDESIGNED[model][factor]
    saved = _exported(root, name, factor)
    return None if saved is None else (*saved, description)


def _exported(root, name, factor):
    """``_saved_run`` of ``experiments/weights/<name>-x<factor>`` as
    ``loading.export_params`` writes it (``.msgpack``, ``-training.csv``, ``.json``)."""
    base = f"experiments/weights/{name}-x{factor}"
    return _saved_run(root, base + ".msgpack", base + "-training.csv", base + ".json")


def _saved_run(root, path, log, cfg):
    """``(path, rows, config)`` of saved weights with their per-epoch log and config
    (paths relative to ``root``), or None when any of the three is missing."""
    if not all(os.path.exists(os.path.join(root, q)) for q in (path, log, cfg)):
        return None
    with open(os.path.join(root, log)) as fh:
        rows = list(csv.DictReader(fh))
    with open(os.path.join(root, cfg)) as fh:
        config = json.load(fh)
    return path, rows, config.get("config", config)


# other trainings of DLCTUS beside the shipped weights: label -> (name, folder); exported
# as experiments/weights/dlctus-<name>-x<f>, checkpoints in experiments/checkpoints/
# <folder>-x<f>/. dlctus-diverse: the shipped weights' first stage (the diverse data
# alone); dlctus-mix: their second stage (game and diverse data half and half);
# dlctus-game: the first stage fine-tuned on the game data alone
DLCTUS_RUNS = {"dlctus-diverse": ("diverse", "diverse"), "dlctus-mix": ("mix", "mix"),
               "dlctus-game": ("game", "game")}


def dlctus_run(factor, label="dlctus-game", root=ROOT):
    """``(path, rows, config)`` of another training of DLCTUS (``DLCTUS_RUNS``) at
    ``factor``: its exported weights (``experiments/weights/dlctus-<name>-x<f>``) or its
    committed checkpoint (``experiments/checkpoints/<folder>-x<f>/``); None if neither."""
    name, folder = DLCTUS_RUNS[label]
    ckpt = f"experiments/checkpoints/{folder}-x{factor}"
    return (_exported(root, f"dlctus-{name}", factor)
            or _saved_run(root, f"{ckpt}/checkpoint.msgpack", f"{ckpt}/metrics.csv",
                          f"{ckpt}/config.json"))


def summarize(rows, epochs_planned):
    """One run's figures from its ``metrics.csv`` rows."""
    psnr = [float(r["val_psnr"]) for r in rows]
    n = len(rows)
    first_of_last_fifth = max(n - max(n // 5, 1) - 1, 0)
    delta = psnr[-1] - psnr[first_of_last_fifth]
    return {"epochs": n, "planned": epochs_planned, "steps": int(rows[-1]["step"]),
            "seconds": sum(float(r["seconds"]) for r in rows), "first": psnr[0],
            "best": max(psnr), "last": psnr[-1], "last_fifth": delta,
            "flat": n == epochs_planned and abs(delta) < 0.1}


def find(model, factor, root="."):
    """``(rows, planned epochs, source)`` of the newest log of a run, or None."""
    cands = []
    for csv_path, cfg_path in (
            (f"experiments/checkpoints/{model}-diverse-x{factor}/metrics.csv",
             f"experiments/checkpoints/{model}-diverse-x{factor}/config.json"),
            (f"experiments/weights/{model}-x{factor}-training.csv",
             f"experiments/weights/{model}-x{factor}.json")):
        p, c = os.path.join(root, csv_path), os.path.join(root, cfg_path)
        if os.path.exists(p) and os.path.exists(c):
            with open(p) as fh:
                rows = list(csv.DictReader(fh))
            with open(c) as fh:
                cfg = json.load(fh)
            cfg = cfg.get("config", cfg)
            if rows and cfg.get("dataset", "").endswith("diverse.h5"):
                # the longer log is the newer (a run only grows; file times mean nothing
                # in a fresh clone), the exported one on a tie (it is the finished run)
                cands.append(((len(rows), "weights/" in csv_path), rows, cfg["epochs"],
                              csv_path))
    if not cands:
        return None
    _, rows, planned, src = max(cands, key=lambda c: c[0])
    return rows, planned, src


def finished(model, factor, epochs, root="."):
    """True if the run's exported log (``experiments/weights/``) is of the ``diverse``
    data and reaches ``epochs``: a finished run, on any machine, with nothing to resume
    or retrain."""
    got = find(model, factor, root)
    return (got is not None and got[2].startswith("experiments/weights/")
            and int(got[0][-1]["epoch"]) >= epochs)


# ---------------------------------------------------------------- independent clips

def external_clips(factor, data_root="data/external"):
    """The independent renderer's clips imported at ``factor``
    (``<clip>-x<factor>.h5`` in ``data_root``, made by
    ``experiments/external/render_mitsuba.py``), sorted by name."""
    suffix = f"-x{factor}.h5"
    names = sorted(f[:-len(suffix)] for f in os.listdir(data_root) if f.endswith(suffix)) \
        if os.path.isdir(data_root) else []
    if not names:
        raise SystemExit(f"{data_root} holds no *{suffix}: python "
                         f"experiments/external/render_mitsuba.py (docs/data.md)")
    return names


def evaluate_clips(entries, factor, data_root="data/external"):
    """Score ``entries`` (``loading.load_all``) on every clip at ``factor``.

    Returns ``(per_clip, pooled)``: ``{clip: {label: summary}}`` and ``{label:
    summary}`` over every frame of every clip (``evaluate.summarize``)."""
    per_clip, pooled = {}, {e.label: {} for e in entries}
    for clip in external_clips(factor, data_root):
        path = os.path.join(data_root, f"{clip}-x{factor}.h5")
        per_frame, _ = evaluate.evaluate(entries, path, factor, progress=False)
        per_clip[clip] = evaluate.summarize(per_frame)
        for lab, d in per_frame.items():
            for k, v in d.items():
                pooled[lab].setdefault(k, []).append(v)
    return per_clip, evaluate.summarize({lab: {k: np.concatenate(v) for k, v in d.items()}
                                         for lab, d in pooled.items()})
