"""Train and export the learned local descriptor `fastmac_exp/models/fcgf_lite.onnx` (see MODEL_CARD.md).

    cd /work/main && python descriptors/fcgf_lite/train.py     # the shipped model: ~22 min on 1 thread
    python descriptors/fcgf_lite/train.py --minutes 2 --pairs 20 --out /tmp/tiny.onnx   # a smoke run

Writes the model (--out), `loss_curve.png` and `<out stem>.train.json` next to it (in descriptors/fcgf_lite/
for the shipped model) (arguments, timings, validation curve). Recipe: 120 synthetic indoor pairs
(SyntheticDataset family 3dmatch, training seed 1000; validation seed 2000; descriptors/evaluate.py uses
seed 0) -> each cloud rotated by a uniform random SO(3) rotation (the GT follows) -> keypoints by voxel
downsampling at 0.05 m and their two-scale LRF patches (fastmac_exp.descriptors.onnx_descriptor: the
runtime's own preprocessing) -> positives = source/target keypoints within 0.75 voxel of each other under GT
-> PatchNet (two-stage PointNet, 32-D unit-norm output) trained with FCGF's hardest-contrastive loss over
in-pair negatives (128 positives + 384 random target keypoints a step, candidates within 0.1 m of the true
match are not negatives) -> the checkpoint with the best validation inlier ratio -> ONNX export (opset 17,
dynamic batch axis) with the preprocessing parameters as metadata, checked against torch to 1e-4 with
onnxruntime.

Everything random is seeded (--seed); training stops at a wall-clock budget (--minutes), so the step
count depends on the machine: pass --steps N for a run that is reproducible step for step.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
DEFAULT_OUT = REPO / "fastmac_exp" / "models" / "fcgf_lite.onnx"
if str(REPO) not in sys.path:  # `python descriptors/fcgf_lite/train.py` from anywhere
    sys.path.insert(0, str(REPO))

import torch  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from torch import nn  # noqa: E402
from tqdm import tqdm  # noqa: E402

from fastmac_exp.descriptors.patches import FEATURES, PatchParams, cloud_patches  # noqa: E402

TRAIN_SEED = 1000
VAL_SEED = 2000
EVAL_SEED = 0  # descriptors/evaluate.py; never used for training or model selection
VOXEL = 0.05
INLIER_THRESHOLD = 0.1


# ----------------------------------------------------------------------------------------------------
# network


class PatchNet(nn.Module):
    """Two-stage PointNet over one patch: per-point MLP, max-pool, local+global MLP, max-pool, head.

    (M, K, C) float32 -> (M, D) float32 unit-norm. Only Linear/ReLU/ReduceMax/Add: a plain ONNX graph.
    """

    def __init__(self, in_ch: int = 3, w1: int = 32, w2: int = 64, w3: int = 128, out_dim: int = 32) -> None:
        super().__init__()
        self.point = nn.Sequential(nn.Linear(in_ch, w1), nn.ReLU(), nn.Linear(w1, w2), nn.ReLU())
        self.local = nn.Linear(w2, w3)
        self.glob = nn.Linear(w2, w3, bias=False)  # == Linear(2 w2, w3) on [local, global], half the cost
        self.head = nn.Sequential(nn.Linear(w3, w3), nn.ReLU(), nn.Linear(w3, out_dim))

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        f = self.point(patches)
        g = f.amax(dim=1)
        h = torch.relu(self.local(f) + self.glob(g).unsqueeze(1)).amax(dim=1)
        o = self.head(h)
        return o / torch.sqrt((o * o).sum(dim=1, keepdim=True) + 1e-12)


# ----------------------------------------------------------------------------------------------------
# data


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform on SO(3) (QR of a Gaussian matrix with the sign fix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def prepare_pair(
    src: np.ndarray,
    tgt: np.ndarray,
    gt: np.ndarray,
    params: PatchParams,
    rng: np.random.Generator,
    rotate: bool = True,
) -> dict:
    """Rotate both clouds at random (the GT follows), cut patches, find the positive keypoint pairs."""
    if rotate:
        rs, rt = random_rotation(rng), random_rotation(rng)
        cs, ct = src.mean(axis=0), tgt.mean(axis=0)
        src = (src - cs) @ rs.T
        tgt = (tgt - ct) @ rt.T
        ts = np.eye(4)
        ts[:3, :3], ts[:3, 3] = rs, -rs @ cs
        tt = np.eye(4)
        tt[:3, :3], tt[:3, 3] = rt, -rt @ ct
        gt = tt @ gt @ np.linalg.inv(ts)
    kp_s, p_s = cloud_patches(src, VOXEL, params)
    kp_t, p_t = cloud_patches(tgt, VOXEL, params)
    kp_sw = kp_s @ gt[:3, :3].T + gt[:3, 3]
    d, j = cKDTree(kp_t).query(kp_sw, k=1)
    pos = np.flatnonzero(d < 0.75 * VOXEL)
    return {
        "src_patches": p_s[pos].astype(np.float16),
        "src_xyz": kp_sw[pos].astype(np.float32),  # source keypoints in the target frame
        "pos_t": j[pos].astype(np.int64),
        "tgt_patches": p_t.astype(np.float16),
        "tgt_xyz": kp_t.astype(np.float32),
    }


def load_pairs(
    num_pairs: int, seed: int, params: PatchParams, cache_dir: str, rng: np.random.Generator, desc: str
) -> list[dict]:
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    ds = SyntheticDataset(family="3dmatch", num_pairs=num_pairs, seed=seed, cache_dir=cache_dir)
    out = []
    for i in tqdm(range(num_pairs), desc=desc, unit="pair"):
        p = ds.load(i)
        item = prepare_pair(p.src_cloud, p.tgt_cloud, p.gt, params, rng)
        if len(item["pos_t"]) >= 32:
            out.append(item)
    return out


# ----------------------------------------------------------------------------------------------------
# losses


def batch_loss(net: PatchNet, item: dict, args: argparse.Namespace, rng: np.random.Generator) -> torch.Tensor:
    n_pos = len(item["pos_t"])
    b = min(args.batch, n_pos)
    sel = rng.choice(n_pos, size=b, replace=False)
    t_pos = item["pos_t"][sel]
    t_extra = rng.choice(len(item["tgt_xyz"]), size=args.negatives, replace=False) if args.negatives else []
    t_all = np.concatenate([t_pos, np.asarray(t_extra, dtype=np.int64)])
    xs = torch.from_numpy(augment(item["src_patches"][sel], rng, args))
    xt = torch.from_numpy(augment(item["tgt_patches"][t_all], rng, args))
    fs, ft = net(xs), net(xt)
    # candidates near the true target are not negatives (a match within the inlier threshold is right)
    txyz = item["tgt_xyz"][t_all]
    near = np.linalg.norm(txyz[None, :, :] - txyz[:b, None, :], axis=2) < args.safe_radius  # (b, n)
    near_t = torch.from_numpy(near)
    eye = torch.zeros_like(near_t)
    eye[:, :b] = torch.eye(b, dtype=torch.bool)
    sim = fs @ ft.T  # cosine similarities (b, n)
    if args.loss == "infonce":
        logits = sim / args.temperature
        logits = logits.masked_fill(near_t & ~eye, float("-inf"))
        loss = nn.functional.cross_entropy(logits, torch.arange(b))
        # symmetric: each positive target against the sampled source anchors
        near_s = torch.from_numpy(
            np.linalg.norm(item["src_xyz"][sel][None] - item["src_xyz"][sel][:, None], axis=2)
            < args.safe_radius
        )
        logits2 = (sim[:, :b].T / args.temperature).masked_fill(
            near_s & ~torch.eye(b, dtype=torch.bool), float("-inf")
        )
        return 0.5 * (loss + nn.functional.cross_entropy(logits2, torch.arange(b)))
    # FCGF hardest-contrastive: squared hinge on positive distance and on the hardest negative's distance
    dist = torch.sqrt(torch.clamp(2.0 - 2.0 * sim, min=1e-7))
    pos = dist[torch.arange(b), torch.arange(b)]
    hardest_t = dist.masked_fill(near_t, float("inf")).amin(dim=1)
    near_s = torch.from_numpy(
        np.linalg.norm(item["src_xyz"][sel][None] - item["src_xyz"][sel][:, None], axis=2) < args.safe_radius
    )
    hardest_s = dist[:, :b].T.masked_fill(near_s, float("inf")).amin(dim=1)
    lp = torch.relu(pos - args.pos_margin).pow(2).mean()
    ln = 0.5 * (
        torch.relu(args.neg_margin - hardest_t).pow(2).mean()
        + torch.relu(args.neg_margin - hardest_s).pow(2).mean()
    )
    return lp + ln


def augment(patches: np.ndarray, rng: np.random.Generator, args: argparse.Namespace) -> np.ndarray:
    x = patches.astype(np.float32)
    if args.drop > 0:  # drop neighbours: replace them by the patch's slot 0 (a duplicate, ignored by max)
        m = rng.random(x.shape[:2]) < args.drop
        m[:, 0] = False
        x = np.where(m[:, :, None], x[:, :1, :], x)
    return x


# ----------------------------------------------------------------------------------------------------
# evaluation during training (validation seed, not the evaluation seed)


def describe(net: PatchNet, patches: np.ndarray, chunk: int = 4096) -> np.ndarray:
    with torch.no_grad():
        return np.concatenate(
            [
                net(torch.from_numpy(patches[i : i + chunk].astype(np.float32))).numpy()
                for i in range(0, len(patches), chunk)
            ]
        )


def validate(net: PatchNet, raw_val: list[tuple], params: PatchParams) -> float:
    """Mean inlier ratio of one-way nearest-neighbour matches over the validation pairs."""
    net.eval()
    irs = []
    for kp_s, p_s, kp_t, p_t, gt in raw_val:
        fs, ft = describe(net, p_s), describe(net, p_t)
        nn_idx = cKDTree(ft).query(fs, k=1)[1]
        err = np.linalg.norm(kp_s @ gt[:3, :3].T + gt[:3, 3] - kp_t[nn_idx], axis=1)
        irs.append(float(np.mean(err < INLIER_THRESHOLD)))
    net.train()
    return float(np.mean(irs))


# ----------------------------------------------------------------------------------------------------
# export


def export_onnx(net: PatchNet, params: PatchParams, path: Path, extra_meta: dict) -> float:
    """torch.onnx.export (opset 17, dynamic batch axis) + metadata; returns max |onnxruntime - torch|."""
    import onnx
    import onnxruntime as ort

    net.eval()
    c = params.channels
    dummy = torch.zeros(2, params.size, c)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.onnx.export(
        net,
        (dummy,),
        str(path),
        input_names=["patches"],
        output_names=["descriptors"],
        dynamic_axes={"patches": {0: "M"}, "descriptors": {0: "M"}},
        opset_version=17,
        dynamo=False,
    )
    model = onnx.load(str(path))
    meta = {
        "fastmac.k": params.k,
        "fastmac.radius_factor": params.radius_factor,
        "fastmac.support_factor": params.support_factor,
        "fastmac.features": params.features,
        "fastmac.k2": params.k2,
        "fastmac.radius_factor2": params.radius_factor2,
        "fastmac.support_factor2": params.support_factor2,
        "fastmac.train_voxel": VOXEL,
        **{f"fastmac.{k}": v for k, v in extra_meta.items()},
    }
    del model.metadata_props[:]
    for k, v in meta.items():
        model.metadata_props.add(key=k, value=str(v))
    model.doc_string = "fcgf_lite: LRF patch PointNet, 32-D unit-norm local descriptors (fastmac-exp)"
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, size=(257, params.size, c)).astype(np.float32)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"patches": x})[0]
    with torch.no_grad():
        want = net(torch.from_numpy(x)).numpy()
    return float(np.abs(got - want).max())


def plot_curve(
    history: list[tuple[int, float]], val: list[tuple[int, float]], path: Path, title: str
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.array([h[0] for h in history])
    loss = np.array([h[1] for h in history])
    w = max(1, len(loss) // 100)
    smooth = np.convolve(loss, np.ones(w) / w, mode="valid")
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(steps, loss, color="0.8", lw=0.5, label="loss (per step)")
    ax.plot(steps[w - 1 :], smooth, color="C0", label=f"loss ({w}-step mean)")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(title)
    if val:
        ax2 = ax.twinx()
        ax2.plot([v[0] for v in val], [v[1] for v in val], "o-", color="C1", label="val inlier ratio")
        ax2.set_ylabel("validation inlier ratio (NN matches)")
        ax2.legend(loc="center right")
    ax.legend(loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------------------------------


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(DEFAULT_OUT))
    ap.add_argument("--curve", default=None, help="loss curve PNG (default: next to --out, loss_curve.png)")
    ap.add_argument("--pairs", type=int, default=120, help="training pairs (synthetic indoor, seed 1000)")
    ap.add_argument("--val-pairs", type=int, default=4, help="validation pairs (seed 2000)")
    ap.add_argument("--cache-dir", default=str(REPO / ".cache" / "synthetic"))
    ap.add_argument("--minutes", type=float, default=20.0, help="training time budget (data prep excluded)")
    ap.add_argument("--steps", type=int, default=0, help="stop after this many steps (0: time budget only)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (2 oversubscribes a shared box)")
    ap.add_argument("--seed", type=int, default=0, help="seeds the network init, rotations and batches")
    ap.add_argument("--k", type=int, default=64)
    ap.add_argument("--radius-factor", type=float, default=6.0)
    ap.add_argument("--support-factor", type=float, default=1.0)
    ap.add_argument("--k2", type=int, default=48, help="points of the second (coarse) scale; 0: one scale")
    ap.add_argument("--radius-factor2", type=float, default=12.0)
    ap.add_argument("--support-factor2", type=float, default=2.5)
    ap.add_argument("--features", default="lrf_n", choices=sorted(FEATURES))
    ap.add_argument("--loss", default="hardest", choices=["infonce", "hardest"])
    ap.add_argument("--batch", type=int, default=128, help="positive pairs per step")
    ap.add_argument("--negatives", type=int, default=384, help="extra random target keypoints per step")
    ap.add_argument("--safe-radius", type=float, default=INLIER_THRESHOLD)
    ap.add_argument("--temperature", type=float, default=0.07)
    ap.add_argument("--pos-margin", type=float, default=0.1)
    ap.add_argument("--neg-margin", type=float, default=1.4)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--drop", type=float, default=0.1)
    ap.add_argument("--val-every", type=int, default=500)
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    t_start = time.time()
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    params = PatchParams(
        k=args.k,
        radius_factor=args.radius_factor,
        support_factor=args.support_factor,
        features=args.features,
        k2=args.k2,
        radius_factor2=args.radius_factor2,
        support_factor2=args.support_factor2,
    )
    out = Path(args.out)
    # the shipped model goes into the package; its records (curve, .train.json) stay beside this script
    records = HERE if out.resolve() == DEFAULT_OUT.resolve() else out.parent
    curve = Path(args.curve) if args.curve else records / "loss_curve.png"

    train = load_pairs(args.pairs, TRAIN_SEED, params, args.cache_dir, rng, "training pairs")
    from fastmac_exp.datasets.synthetic import SyntheticDataset

    vds = SyntheticDataset(
        family="3dmatch", num_pairs=args.val_pairs, seed=VAL_SEED, cache_dir=args.cache_dir
    )
    raw_val = []
    for i in range(args.val_pairs):
        p = vds.load(i)
        kp_s, p_s = cloud_patches(p.src_cloud, VOXEL, params)
        kp_t, p_t = cloud_patches(p.tgt_cloud, VOXEL, params)
        raw_val.append((kp_s, p_s, kp_t, p_t, p.gt))
    t_data = time.time() - t_start
    print(f"data: {len(train)} training pairs, {len(raw_val)} validation pairs in {t_data:.0f} s", flush=True)

    net = PatchNet(in_ch=params.channels)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    budget = args.minutes * 60.0
    history: list[tuple[int, float]] = []
    val: list[tuple[int, float]] = [(0, validate(net, raw_val, params))]
    best = (val[0][1], 0, {k: v.clone() for k, v in net.state_dict().items()})
    t0 = time.time()
    bar = tqdm(total=args.steps or None, desc="training", unit="step")
    step = 0
    while True:
        elapsed = time.time() - t0
        if (args.steps and step >= args.steps) or elapsed >= budget:
            break
        frac = elapsed / budget if not args.steps else step / args.steps
        for g in opt.param_groups:  # cosine decay over the budget
            g["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(frac, 1.0))))
        item = train[rng.integers(len(train))]
        loss = batch_loss(net, item, args, rng)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        history.append((step, loss.item()))
        bar.update(1)
        if step % 50 == 0:
            bar.set_postfix(loss=f"{np.mean([h[1] for h in history[-50:]]):.3f}", val=f"{val[-1][1]:.3f}")
        if step % args.val_every == 0:
            val.append((step, validate(net, raw_val, params)))
            if val[-1][1] >= best[0]:
                best = (val[-1][1], step, {k: v.clone() for k, v in net.state_dict().items()})
    bar.close()
    val.append((step, validate(net, raw_val, params)))
    if val[-1][1] >= best[0]:
        best = (val[-1][1], step, {k: v.clone() for k, v in net.state_dict().items()})
    net.load_state_dict(best[2])
    t_train = time.time() - t0
    print(
        f"trained {step} steps in {t_train / 60:.1f} min; best validation inlier ratio {best[0]:.4f} "
        f"at step {best[1]}",
        flush=True,
    )

    meta = {
        "loss": args.loss,
        "train_seed": TRAIN_SEED,
        "train_pairs": len(train),
        "steps": step,
        "selected_step": best[1],
        "val_inlier_ratio": round(best[0], 4),
        "recipe_seed": args.seed,
    }
    err = export_onnx(net, params, out, meta)
    print(f"exported {out} ({out.stat().st_size / 1e3:.0f} kB); max |onnxruntime - torch| = {err:.2e}")
    if err > 1e-4:
        raise SystemExit(f"ONNX export check failed: max difference {err:.2e} > 1e-4")
    plot_curve(history, val, curve, f"fcgf_lite ({args.loss}, {args.features}, K={args.k})")
    summary = {
        "params": asdict(params),
        "args": vars(args),
        "steps": step,
        "data_s": round(t_data, 1),
        "train_s": round(t_train, 1),
        "total_s": round(time.time() - t_start, 1),
        "val": val,
        "selected_step": best[1],
        "onnx_max_abs_diff": err,
    }
    (records / (out.stem + ".train.json")).write_text(json.dumps(summary, indent=1))
    print(f"loss curve: {curve}; total {summary['total_s'] / 60:.1f} min")


if __name__ == "__main__":
    main()
