#!/usr/bin/env python3
"""Trains the general AdaIN decoder that ships in assets/decoder/ on a GPU with PyTorch.

`stylenerf stylize train-decoder` trains the same decoder with the engine's own code, but on
two CPU cores it gets through a few hundred small steps an hour (docs/BENCHMARKS.md, "A general
2D teacher trained on a CPU"). This script is the offline, one-time GPU path for the bundled
asset. It reproduces the engine's network exactly and nothing else:

- the encoder is read from `stylenerf weights export` (the weights as the engine runs them:
  RGB in [0, 1] in, preprocessing folded into conv1_1, activations normalised), so the decoder
  learns the very features the engine computes;
- the decoder is the encoder's mirror as in engine/src/style2d/decoder.rs (reflection padding,
  3x3 convolutions, ReLU but after the last, 2x nearest upsampling where the encoder pooled),
  saved with the engine's tensor names and metadata (`decoder.{k}.weight`, `format`, `arch`,
  `encoder`), so `Decoder::load` reads it;
- the losses are engine/src/style2d/losses.rs: content = MSE(relu4_1(out), AdaIN target),
  style = sum over relu1_1..relu4_1 of MSE(channel mean) + MSE(channel std), with the unbiased
  variance and eps = 1e-5 inside the root (engine/src/style2d/adain.rs);
- the sampling is engine/src/style2d/corpus.rs: square crops of log-uniform side between `crop`
  and the image's shorter side, resized, mirrored half the time; style crops hue-rotated (YIQ)
  with probability `hue_jitter`.

The images live on the GPU (shrunk to a longest side of 512 once), crops are cut there, and the
networks run in bfloat16 autocast with the statistics and losses in float32. Training stops
after `--minutes`; a checkpoint of the decoder (float16, the shipped format) and a preview
sheet are written every `--checkpoint-seconds` and at the end, so a run cut short still leaves
its latest weights. Run it with `--selftest` on a CPU to check the decoder file against the
engine (see docs/STYLE2D.md for the whole recipe).
"""

import argparse
import json
import math
import os
import random
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from safetensors import safe_open
from safetensors.torch import save_file

FORMAT_TAG = "stylenerf-adain-decoder/1"
EPS = 1e-5
EXTS = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")

# (name, c_in, c_out, pool_before, tap), as engine/src/style2d/arch.rs.
VGG16 = [
    ("conv1_1", 3, 64, False, True),
    ("conv1_2", 64, 64, False, False),
    ("conv2_1", 64, 128, True, True),
    ("conv2_2", 128, 128, False, False),
    ("conv3_1", 128, 256, True, True),
    ("conv3_2", 256, 256, False, False),
    ("conv3_3", 256, 256, False, False),
    ("conv4_1", 256, 512, True, True),
]
VGG19 = VGG16[:7] + [("conv3_4", 256, 256, False, False), VGG16[7]]


class Encoder(torch.nn.Module):
    """The frozen encoder read from `stylenerf weights export`."""

    def __init__(self, path):
        super().__init__()
        with safe_open(path, "pt") as f:
            meta = f.metadata() or {}
            if meta.get("activations") != "normalised" or meta.get("channel_order") != "rgb":
                sys.exit(f"{path}: not an exported encoder (run `stylenerf weights export`)")
            if float(meta["scale"]) != 1.0 or meta["mean"] != "0,0,0" or meta["std"] != "1,1,1":
                sys.exit(f"{path}: expected identity preprocessing, found {meta}")
            self.arch = meta["arch"]
            self.source = meta.get("source", "")
            spec = {"vgg16": VGG16, "vgg19": VGG19}[self.arch]
            self.spec = spec
            for name, *_ in spec:
                self.register_buffer(name + "_w", f.get_tensor(name + ".weight").float())
                self.register_buffer(name + "_b", f.get_tensor(name + ".bias").float())

    def forward(self, x):
        taps = []
        h = x
        for name, _, _, pool, tap in self.spec:
            if pool:
                h = F.max_pool2d(h, 2)
            h = F.conv2d(F.pad(h, (1, 1, 1, 1), mode="reflect"), getattr(self, name + "_w"),
                         getattr(self, name + "_b"))
            h = F.relu(h)
            if tap:
                taps.append(h)
                if len(taps) == 4:
                    break
        return taps


def mirror(spec):
    """Decoder steps (c_in, c_out, relu, upsample_after), as decoder.rs `mirror`."""
    n = len(spec)
    return [(c_out, c_in, k + 1 < n, pool) for k, (_, c_in, c_out, pool, _) in
            enumerate(reversed(spec))]


class Decoder(torch.nn.Module):
    def __init__(self, spec, seed):
        super().__init__()
        self.steps = mirror(spec)
        self.convs = torch.nn.ModuleList()
        g = torch.Generator().manual_seed(seed)
        for c_in, c_out, relu, _ in self.steps:
            conv = torch.nn.Conv2d(c_in, c_out, 3, padding=1, padding_mode="reflect")
            # He-uniform, the last layer scaled by 0.1 with a mid-grey bias (Decoder::new).
            bound = math.sqrt(6.0 / (c_in * 9)) * (1.0 if relu else 0.1)
            with torch.no_grad():
                conv.weight.copy_((torch.rand(conv.weight.shape, generator=g) * 2 - 1) * bound)
                conv.bias.fill_(0.0 if relu else 0.5)
            self.convs.append(conv)

    def forward(self, h):
        for conv, (_, _, relu, up) in zip(self.convs, self.steps):
            h = conv(h)
            if relu:
                h = F.relu(h)
            if up:
                h = F.interpolate(h, scale_factor=2, mode="nearest")
        return h

    def state(self, dtype):
        out = {}
        for k, conv in enumerate(self.convs):
            out[f"decoder.{k}.weight"] = conv.weight.detach().to("cpu", dtype).contiguous()
            out[f"decoder.{k}.bias"] = conv.bias.detach().to("cpu", dtype).contiguous()
        return out

    def save(self, path, arch, encoder_source, dtype=torch.float16):
        tmp = path + ".tmp"
        save_file(self.state(dtype), tmp,
                  metadata={"format": FORMAT_TAG, "arch": arch, "encoder": encoder_source})
        os.replace(tmp, path)

    def load(self, path):
        with safe_open(path, "pt") as f:
            for k, conv in enumerate(self.convs):
                conv.weight.data.copy_(f.get_tensor(f"decoder.{k}.weight").float())
                conv.bias.data.copy_(f.get_tensor(f"decoder.{k}.bias").float())


def stats(feat):
    """Channel mean and unbiased std (+eps inside the root), float32, [B, C, 1, 1]."""
    b, c = feat.shape[:2]
    flat = feat.float().reshape(b, c, -1)
    mean = flat.mean(2)
    var = flat.var(2, unbiased=True)
    return mean.reshape(b, c, 1, 1), (var + EPS).sqrt().reshape(b, c, 1, 1)


def adain(content, style_mean, style_std):
    m, s = stats(content)
    return (content.float() - m) / s * style_std + style_mean


def losses(enc, dec, content, style):
    with torch.no_grad():
        s_stats = [stats(f) for f in enc(style)]
        target = adain(enc(content)[3], *s_stats[3])
    out = dec(target)
    feats = enc(out)
    l_content = F.mse_loss(feats[3].float(), target)
    l_style = 0.0
    for f, (sm, ss) in zip(feats, s_stats):
        m, s = stats(f)
        l_style = l_style + F.mse_loss(m, sm) + F.mse_loss(s, ss)
    return l_content, l_style, out


def list_images(paths):
    files = []
    for p in paths:
        if os.path.isdir(p):
            for root, _, names in os.walk(p):
                files += [os.path.join(root, n) for n in sorted(names)
                          if n.lower().endswith(EXTS)]
        else:
            files.append(p)
    return sorted(files)


def load_images(paths, max_side, min_side, device):
    """uint8 [3, H, W] tensors on `device`, shrunk (never enlarged) to `max_side`."""
    out, names = [], []
    for p in list_images(paths):
        try:
            img = Image.open(p).convert("RGB")
        except Exception as e:  # a file PIL cannot read is named and skipped
            print(f"skipping {p}: {e}", file=sys.stderr)
            continue
        w, h = img.size
        s = max_side / max(w, h)
        if s < 1:
            img = img.resize((max(1, round(w * s)), max(1, round(h * s))), Image.BILINEAR,
                             reducing_gap=None)
        if min(img.size) < min_side:
            print(f"skipping {p}: {img.size} is smaller than {min_side}", file=sys.stderr)
            continue
        t = torch.from_numpy(np.asarray(img).copy()).permute(2, 0, 1).contiguous()
        out.append(t.to(device))
        names.append(p)
    return out, names


YIQ = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
RGB = torch.tensor([[1.0, 0.956, 0.621], [1.0, -0.272, -0.647], [1.0, -1.106, 1.703]])


def rotate_hue(x, angle):
    """corpus.rs `rotate_hue`: rotate chroma in YIQ by `angle`, keep luma, clamp."""
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    m = (RGB @ rot @ YIQ).to(x.device, x.dtype)
    return torch.einsum("ij,jhw->ihw", m, x).clamp(0, 1)


def random_crop(img, crop, rng):
    _, h, w = img.shape
    short = min(h, w)
    lo = min(crop, short)
    side = int(round(lo * (short / lo) ** rng.random()))
    side = max(1, min(side, short))
    y = rng.randrange(h - side + 1)
    x = rng.randrange(w - side + 1)
    patch = img[:, y:y + side, x:x + side].float().unsqueeze(0) / 255.0
    patch = F.interpolate(patch, size=(crop, crop), mode="bilinear", antialias=True,
                          align_corners=False)[0].clamp(0, 1)
    if rng.random() < 0.5:
        patch = patch.flip(2)
    return patch


def draw(images, n, crop, rng, hue_jitter=0.0):
    crops = []
    for _ in range(n):
        c = random_crop(images[rng.randrange(len(images))], crop, rng)
        if rng.random() < hue_jitter:
            c = rotate_hue(c, rng.random() * 2 * math.pi)
        crops.append(c)
    return torch.stack(crops)


def preview(enc, dec, pairs, path):
    """Rows of content | style | output, as a PNG."""
    rows = []
    with torch.no_grad(), torch.autocast(pairs[0][0].device.type, torch.bfloat16,
                                         enabled=pairs[0][0].is_cuda):
        for c, s in pairs:
            out = dec(adain(enc(c)[3], *stats(enc(s)[3]))).float().clamp(0, 1)
            rows.append(torch.cat([c[0], s[0], out[0]], 2))
    grid = (torch.cat(rows, 1).permute(1, 2, 0).cpu().numpy() * 255).round().astype(np.uint8)
    Image.fromarray(grid).save(path)


def selftest(args):
    """Writes a decoder with random weights and its output on a fixed input, so the engine
    can check it computes the same (engine/tests/decoder_asset.rs reads both)."""
    enc = Encoder(args.encoder)
    dec = Decoder(enc.spec, args.seed)
    os.makedirs(args.out, exist_ok=True)
    dec.save(os.path.join(args.out, "decoder.safetensors"), enc.arch, enc.source,
             dtype=torch.float32)
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 32), torch.linspace(0, 1, 48), indexing="ij")
    img = torch.stack([xx, yy, 0.5 + 0.5 * torch.sin(6 * xx * yy)]).unsqueeze(0)
    img = (img * 255).round() / 255  # exactly an 8-bit image
    Image.fromarray((img[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(
        os.path.join(args.out, "input.png"))
    with torch.no_grad():
        out = dec(enc(img)[3])
    save_file({"input": img.contiguous(), "output": out.contiguous()},
              os.path.join(args.out, "io.safetensors"))
    print(f"selftest: wrote {args.out}/decoder.safetensors and io.safetensors")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--encoder", required=True, help="`stylenerf weights export` output")
    ap.add_argument("--content", nargs="+", default=[], help="content image files or folders")
    ap.add_argument("--style", nargs="+", default=[], help="style image files or folders")
    ap.add_argument("--out", required=True)
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--lr", type=float, default=2e-4)
    ap.add_argument("--final-lr-ratio", type=float, default=0.2)
    ap.add_argument("--warmup-steps", type=int, default=200)
    ap.add_argument("--style-weight", type=float, default=1.0)
    ap.add_argument("--hue-jitter", type=float, default=0.5)
    ap.add_argument("--max-side", type=int, default=512)
    ap.add_argument("--checkpoint-seconds", type=float, default=120.0)
    ap.add_argument("--init", help="a decoder file to start from")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--selftest", action="store_true")
    args = ap.parse_args()
    if args.selftest:
        return selftest(args)
    if args.crop % 8:
        sys.exit("--crop must be a multiple of 8")
    torch.manual_seed(args.seed)
    rng = random.Random(args.seed)
    dev = torch.device(args.device)
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True

    enc = Encoder(args.encoder).to(dev).eval()
    dec = Decoder(enc.spec, args.seed).to(dev)
    if args.init:
        dec.load(args.init)
    content, cnames = load_images(args.content, args.max_side, args.crop // 2, dev)
    styles, snames = load_images(args.style, args.max_side, args.crop // 2, dev)
    if not content or not styles:
        sys.exit("need at least one content image and one style image")
    print(f"{len(content)} content images, {len(styles)} style images, device {dev}",
          flush=True)
    os.makedirs(args.out, exist_ok=True)
    opt = torch.optim.Adam(dec.parameters(), lr=args.lr)
    # Fixed preview pairs: the same four every checkpoint.
    prng = random.Random(12345)
    pairs = [(draw(content, 1, args.crop, prng), draw(styles, 1, args.crop, prng))
             for _ in range(4)]
    budget = args.minutes * 60
    start = last_ckpt = time.time()
    log = []
    step = 0
    run_c = run_s = None
    amp = dev.type == "cuda"
    while True:
        elapsed = time.time() - start
        if elapsed >= budget:
            break
        frac = elapsed / budget
        lr = args.lr * min(1.0, (step + 1) / args.warmup_steps) * args.final_lr_ratio ** frac
        for g in opt.param_groups:
            g["lr"] = lr
        c = draw(content, args.batch, args.crop, rng)
        s = draw(styles, args.batch, args.crop, rng, args.hue_jitter)
        with torch.autocast(dev.type, torch.bfloat16, enabled=amp):
            lc, ls, _ = losses(enc, dec, c, s)
            loss = lc + args.style_weight * ls
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        step += 1
        if step % 50 == 0:
            lc, ls = lc.item(), ls.item()
            run_c = lc if run_c is None else 0.9 * run_c + 0.1 * lc
            run_s = ls if run_s is None else 0.9 * run_s + 0.1 * ls
            log.append({"step": step, "seconds": round(time.time() - start, 1),
                        "content": lc, "style": ls, "lr": lr})
            if step % 500 == 0:
                print(f"step {step} {time.time() - start:.0f}s content {run_c:.3f} "
                      f"style {run_s:.3f} lr {lr:.2e}", flush=True)
        if time.time() - last_ckpt > args.checkpoint_seconds:
            dec.save(os.path.join(args.out, "decoder.safetensors"), enc.arch, enc.source)
            last_ckpt = time.time()
    dec.save(os.path.join(args.out, "decoder.safetensors"), enc.arch, enc.source)
    preview(enc, dec, pairs, os.path.join(args.out, "preview.png"))
    summary = {
        "steps": step, "seconds": round(time.time() - start, 1),
        "content_images": len(content), "style_images": len(styles),
        "args": {k: v for k, v in vars(args).items() if k not in ("content", "style")},
        "torch": torch.__version__,
        "device_name": torch.cuda.get_device_name() if amp else "cpu",
        "log": log,
    }
    with open(os.path.join(args.out, "train_log.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(f"done: {step} steps in {summary['seconds']} s", flush=True)


if __name__ == "__main__":
    main()
