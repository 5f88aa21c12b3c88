"""Regenerate ``docs/results.md`` from the experiments' outputs, optionally running
them first.

    python experiments/make_results.py            # assemble from docs/results/*/
    python experiments/make_results.py --run      # run every experiment, then assemble
    python experiments/make_results.py --run --quick   # small settings, minutes

Each section shows the table an experiment wrote, its plot, and the exact command and
hardware that produced it (both recorded by the experiment itself).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

from common import RESULTS, ROOT, runs_so_far

SECTIONS = [
    ("comparison-table", "Every system on the four test families (randomized scenes, "
     "hand-made scenes, an independent renderer, held-out game levels)", None),
    ("static-hold", "Static holds on the held-out families (`python "
     "experiments/static_hold.py`)", "hold_x4.png"),
    ("evaluation", "Evaluation on the `default` data's test split (earlier weights)",
     "per_frame_x4.png"),
    ("pareto", "What accuracy costs in time (and thesis Tables 13 and 14 at inference)",
     "pareto.png"),
    ("collapse-probe", "Which learning rate the ablations can train at (`python "
     "experiments/collapse_probe.py`)", None),
    ("ablation-accumulation", "Accumulation buffer on/off at the `diverse` recipe, over "
     "seeds (thesis Table 16; `python experiments/ablations.py --study accumulation`)", None),
    ("ablation-warp", "Bilinear against bicubic reprojection at the `diverse` recipe "
     "(thesis Table 13; `python experiments/ablations.py --study warp`)", None),
    ("ablation-theta", "L1 against L_st-linear at the `diverse` recipe (thesis Table 10; "
     "`python experiments/ablations.py --study theta`)", None),
    ("theta", "The θ sweep (thesis Table 10)", "theta.png"),
    ("seqlen", "Sequence length, BPTT, truncated BPTT and remat", "seqlen.png"),
    ("stability", "Long-run numerical stability", "stability.png"),
]

RUNS = {
    "full": [["experiments/comparison_table.py"],
             ["experiments/static_hold.py"],
             ["experiments/sweep_theta.py"],
             ["experiments/pareto.py"],
             ["experiments/sweep_seqlen.py"],
             ["experiments/stability.py"]],
    "quick": [["experiments/pareto.py", "--sizes", "256", "720p", "--max-videos", "4"],
              ["experiments/sweep_theta.py", "--epochs", "1", "--steps-per-epoch", "40",
               "--max-videos", "4"],
              ["experiments/sweep_seqlen.py", "--lengths", "2", "4", "8", "--steps", "20",
               "--long-frames", "320", "--long-size", "64", "--max-videos", "2"],
              ["experiments/stability.py", "--frames", "600", "--size", "64"]],
}

# Reading notes that hold for any run of the section
NOTES = {
    "evaluation": "This table is the `default` data's test split with the systems' "
                  "earlier weights (DLCTUS trained on the built-in scenes, the comparison "
                  "systems' short first runs); the table above replaces it.",
    "pareto": "The warp, dtype and dilation rows run the shipped DLCTUS weights (trained "
              "with the 16-tap bicubic warp, float32) with that setting switched at "
              "inference, as the thesis's Tables 13 and 14 did; networks trained with each "
              "warp and with and without the accumulation buffer are the ablation sections "
              "below. Timings are medians of 3 on the 2-core machine with no other job of "
              "ours running (see `docs/performance.md` for ratios timed side by side); "
              "quality columns are on the shipped (DLCTUS) or `experiments/weights/` "
              "parameters.",
    "collapse-probe": "A collapsed network's blend output lies outside [0, 1] at every "
                      "pixel (100% in the column above), so its clamp passes no gradient "
                      "and the network never moves again (`docs/weights.md`). At the "
                      "`diverse` preset's learning rate (1e-3) this happened within the "
                      "first epoch to every ablation network without the buffer and to "
                      "2 of 5 with it; at 3e-4 to 1 of 5 (a seed that collapsed at 1e-3 "
                      "too). The ablations below therefore train at 3e-4 "
                      "(`experiments/ablations.py --lr`, its default) and replace a "
                      "collapsed seed with the next one. The thesis trained at 1e-4.",
    "ablation-accumulation": "The ablation networks train 2,000 steps at crop 128 over 16 "
                             "frames, the thesis's 200 epochs at crop 256 over 30 frames: "
                             "the table measures each option early in training, and a gap "
                             "within about two standard errors of zero is not a difference "
                             "these seeds can tell.",
    "ablation-warp": "Each network here trains with the warp it is scored with; the "
                     "Pareto section above switches the warp of the shipped weights at "
                     "inference, as the thesis's Table 13 did.",
    "ablation-theta": "θ weights L_st-linear's temporal term: the temporal error column "
                      "(θ=1) is what a larger θ buys and PSNR what it costs. The L1 row is "
                      "the accumulation study's \"with buffer\" run of the same seed "
                      "(`run_of`). A single seed has no spread, and a θ network's score can "
                      "move between seeds by more than the accumulation and warp studies' "
                      "0.06-0.16 dB: seed 1 of θ=0.1 and 0.5 has trained since (checkpoints "
                      "in `experiments/checkpoints/ablation-theta/`), and `--seeds 0 1 2` "
                      "resumes these runs, trains the rest and writes the table over them.",
    "seqlen": "Seconds per step compare rows within one run: the machine may have been "
              "shared (the run shown shared it with a training job).",
}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--run", action="store_true")
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    if args.run:
        for cmd in RUNS["quick" if args.quick else "full"]:
            print("+", " ".join(cmd), flush=True)
            subprocess.run([sys.executable] + cmd, cwd=ROOT, check=True)
    parts = ["# Results", "",
             "Every table below is written by the experiment named under it, with its command "
             "and hardware; `python experiments/make_results.py --run` regenerates them all "
             "(`--quick` for small settings). Sections not yet run say so.", ""]
    for name, title, img in SECTIONS:
        parts += [f"## {title}", ""]
        found = [os.path.join(RESULTS, name, f) for f in ("result.md", "results.md")
                 if os.path.exists(os.path.join(RESULTS, name, f))]
        md = found[0] if found else None
        if md:
            with open(md) as fh:
                parts.append(fh.read().strip())
            if img and os.path.exists(os.path.join(RESULTS, name, img)):
                parts += ["", f"![{name}](results/{name}/{img})"]
            if name in NOTES:
                parts += ["", NOTES[name]]
        else:
            so_far = runs_so_far(name.split("-", 1)[1]) if name.startswith("ablation-") else []
            parts += so_far or [f"Not run yet: see `experiments/` (`{name}`)."]
        parts.append("")
    with open(os.path.join(ROOT, "docs", "results.md"), "w") as fh:
        fh.write("\n".join(parts))
    print("wrote docs/results.md")


if __name__ == "__main__":
    main()
