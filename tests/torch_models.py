"""Independent PyTorch forwards of NSRR and of the KPN network (tests only), NCHW,
built on torch's conv2d / max_pool2d / interpolate / grid_sample / softmax."""

import numpy as np
import torch
import torch.nn.functional as F


def t(x):
    return torch.from_numpy(np.array(x, dtype=np.float32, order="C"))  # a writable copy


def nchw(x):
    return t(np.moveaxis(np.asarray(x), -1, 1))


def conv(x, p, padding="same"):
    w = t(np.asarray(p["kernel"]).transpose(3, 2, 0, 1))
    return F.conv2d(x, w, t(p["bias"]), padding=padding)


def stack(ps, x, last_relu=True):
    for i, p in enumerate(ps):
        x = conv(x, p)
        if last_relu or i < len(ps) - 1:
            x = F.relu(x)
    return x


def zero_up(x, jitter, f):
    b, c, h, w = x.shape
    out = torch.zeros(b, c, h * f, w * f)
    cell = np.clip(np.floor(np.asarray(jitter) * f).astype(int), 0, f - 1)
    for i in range(b):
        out[i, :, cell[i, 1]::f, cell[i, 0]::f] = x[i]
    return out


def warp_border_masked(img, motion_lr, f):
    """Bilinear backward warp at HR (border taps), zero where the point leaves the frame."""
    b, c, hh, ww = img.shape
    mv = F.interpolate(motion_lr, scale_factor=f, mode="bilinear", align_corners=False) * f
    px = torch.arange(ww, dtype=torch.float32)[None, None, :] + 0.5 + mv[:, 0]
    py = torch.arange(hh, dtype=torch.float32)[None, :, None] + 0.5 + mv[:, 1]
    grid = torch.stack([2 * px / ww - 1, 2 * py / hh - 1], -1)
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    inside = ((grid >= -1) & (grid <= 1)).all(-1)[:, None]
    return torch.where(inside, out, torch.zeros_like(out))


def nsrr_step(params, previous, color, depth, motion, jitter, f, frames=4, scale=10.0,
              near=0.1, far=100.0):
    """One NSRR step; returns (rgb, new previous), NCHW."""
    lin = (near * far / (far - depth * (far - near)) - near) / (far - near)
    rgbd = torch.cat([color, lin], 1)
    cur = zero_up(torch.cat([rgbd, stack(params["extract_current"], rgbd)], 1), jitter, f)
    prev_f = zero_up(torch.cat([rgbd, stack(params["extract_previous"], rgbd)], 1), jitter, f)
    warped = warp_border_masked(previous, motion, f)
    x = torch.cat([cur[:, :4]] + [warped[:, 12 * i:12 * i + 4] for i in range(frames)], 1)
    wts = scale * (torch.tanh(stack(params["reweight"], x, last_relu=False)) + 1) / 2
    feats = [cur] + [warped[:, 12 * i:12 * (i + 1)] * wts[:, i:i + 1] for i in range(frames)]
    u = params["unet"]
    r = F.relu
    s1 = r(conv(r(conv(torch.cat(feats, 1), u[0])), u[1]))
    s2 = r(conv(r(conv(F.max_pool2d(s1, 2), u[2])), u[3]))
    s3 = r(conv(r(conv(F.max_pool2d(s2, 2), u[4])), u[5]))
    up = lambda z: F.interpolate(z, scale_factor=2, mode="bilinear", align_corners=False)  # noqa: E731
    d2 = r(conv(r(conv(torch.cat([up(s3), s2], 1), u[6])), u[7]))
    out = conv(r(conv(torch.cat([up(d2), s1], 1), u[8])), u[9])
    return out, torch.cat([prev_f, warped[:, :12 * (frames - 1)]], 1), wts


def _pick(p, phase):
    return {"kernel": np.asarray(p["kernel"])[phase], "bias": np.asarray(p["bias"])[phase]}


def kpn_forward(params, x, jau, rep, phase):
    """The KPN network and its two 5x5 kernels for one sample (batch 1), NCHW."""
    h = F.relu(conv(x, params["conv1"]))
    h = F.relu(conv(h, _pick(params["conv2"], phase)))
    h = F.relu(conv(h, _pick(params["conv3"], phase)))
    hidden = conv(h, params["hidden"])
    w = torch.softmax(conv(h, _pick(params["kernel"], phase)), 1)  # [1,50,H,W]
    def apply(img, wk):
        patches = F.unfold(img, 5, padding=2).view(1, img.shape[1], 25, *img.shape[2:])
        return (patches * wk[:, None]).sum(2)
    out = apply(jau, w[:, :25]) + apply(rep[:, :3], w[:, 25:])
    return out, hidden, w
