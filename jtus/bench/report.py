"""The bench's report as Markdown tables (``python -m jtus.bench``)."""

from __future__ import annotations

from jtus import hostmem

NONE = "–"  # a cell that does not apply (no network, no reference)


def _f(r, key, fmt):
    """``r[key]`` formatted, or a dash where the record has no such figure."""
    v = r.get(key)
    return NONE if v is None or v != v else format(v, fmt)


def _peak(report):
    p = report["peak"]
    return [f"Peak (same run): matmul 2048^3 {p['matmul_gflops']:.1f} GFLOP/s; "
            f"3x3 conv 32->32 at 270x480 {p['conv_dlctus_gflops']:.1f} GFLOP/s; "
            f"3x3 conv 64->64 at 256x256 {p['conv_64_gflops']:.1f} GFLOP/s.", ""]


def _infer(report):
    lines = ["| model | size | factor | dtype | formulation | kernels | ms/frame | GFLOP/frame | "
             "GFLOP/s | network ms | network GFLOP/s | % of conv peak | torch ms | "
             "torch/jtus |",
             "| --- " * 14 + "|"]
    conv_peak = report.get("peak", {}).get("conv_dlctus_gflops")
    for r in report["infer"]:
        pct = (f"{100 * r['network_gflops'] / conv_peak:.0f}%"
               if conv_peak and "network_gflops" in r else "")
        lines.append(
            f"| {r['model']} | {r['size']} | {r['factor']}x | {r['dtype']} | "
            f"{r.get('formulation', '')} | {r.get('kernels', '')} | {r['ms']:.1f} | "
            f"{r['gflop']:.2f} | {r['gflops']:.1f} | {_f(r, 'network_ms', '.1f')} | "
            f"{_f(r, 'network_gflops', '.1f')} | {pct or NONE} | {_f(r, 'torch_ms', '.1f')} | "
            f"{_f(r, 'torch_over_jtus', '.2f')} |")
    return lines + ["", "The step, the network alone and the PyTorch reference are timed in "
                    "turn (medians of alternating runs). The network is the step's "
                    "convolutions jitted on their own: its time is part of the step's, but "
                    "a separate program can be scheduled differently, so on a busy machine "
                    "it can come out a little above the step. A dash: the figure does not "
                    "apply (no network, no PyTorch reference).", ""]


def _devices(n, cores=None):
    """How the step ran: the batch split over ``n`` devices, said to be one per core
    only when the report's machine has ``n`` cores."""
    if n == 1:
        return "; one XLA device"
    return f"; the batch split over {n} XLA CPU devices{' (one per core)' if n == cores else ''}"


def _train(report):
    lines = ["| model | warp | kernels | conv backward | s/step | frames/s | torch s/step | "
             "torch frames/s | torch/jtus | step memory (MiB) | x bound at conv peak |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["train"]:
        bound = r.get("bound_s_at_conv_peak")
        lines.append(
            f"| {r['model']} | {r['warp']} | {r.get('kernels', '-')} | "
            f"{r.get('conv_backward', '-')} | {r['s_per_step']:.3f} | "
            f"{r['frames_per_s']:.1f} | "
            f"{_f(r, 'torch_s_per_step', '.3f')} | {_f(r, 'torch_frames_per_s', '.1f')} | "
            f"{_f(r, 'torch_over_jtus', '.2f')} | {_f(r, 'peak_mib', '.0f')} | "
            f"{format(r['s_per_step'] / bound, '.2f') if bound else NONE} |")
    r = report["train"][0]
    devices = _devices(r.get("devices", 1), report.get("hardware", {}).get("cores"))
    scan = "unrolled" if r["unroll"] else "rolled"
    remat = f", remat {r['remat']}" if r["remat"] else ""
    lines += ["", f"Training step: {r['factor']}x, crop {r['crop']}, batch {r['batch']}, "
              f"sequence {r['seq']}, loss on the last {r['loss_frames']}, Adam; {scan} scan"
              f"{remat}"
              f"{', preparation hoisted' if r.get('hoist') else ''}"
              f"{devices}. Frames/s counts batch x "
              f"sequence per step; step memory is XLA's plan (temporaries, arguments, "
              f"outputs); the bound is 3x the forward FLOPs at the measured convolution "
              f"peak, which no implementation on this machine's convolutions beats."]
    return lines


def markdown(report):
    hw = report["hardware"]
    lines = [f"Hardware: {hw['cpu']}, {hw['cores']} cores, JAX {hw['jax']} on {hw['backend']}."]
    if "host_memory" in report:
        lines.append(f"Host memory: {hostmem.describe(report['host_memory'])}; the PyTorch "
                     f"references, timed in the same process, share it.")
    lines += [f"Command: `{report['command']}`", ""]
    if "peak" in report:
        lines += _peak(report)
    if "infer" in report:
        lines += _infer(report)
    if "train" in report:
        lines += _train(report)
    return "\n".join(lines).rstrip()
