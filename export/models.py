"""The exportable models: R18 reference depth net and the BEVDepth-style depth branch, with fixed I/O names.

Inputs and outputs (stable names; B = batch, dynamic; N = cameras, dynamic for ``bevdepth``):

``r18``  (image size dynamic, multiples of 32)
    image     float32 [B, 3, H, W]  RGB in [0, 1] (ImageNet normalisation is inside the graph)
    prior     float32 [B, 1, H, W]  metric depth prior in metres, 0 = no prior
    depth     float32 [B, 1, H, W]  metric depth in metres (output)

``bevdepth``  (feature size h x w fixed at export; image size = 16 h x 16 w)
    features        float32 [B*N, C_in, h, w]  image features at stride 16 (one sweep)
    prior           float32 [B, N, 16h, 16w]   metric prior of that sweep at the augmented image size, 0 = none
    intrin_mats     float32 [B, S, N, 4, 4]    camera intrinsics, BEVDepth's mats_dict layout (S >= 1
    ida_mats        float32 [B, S, N, 4, 4]    image-augmentation matrices      sweeps; like BEVDepth's
    sensor2ego_mats float32 [B, S, N, 4, 4]    camera-to-ego transforms         DepthNet the graph reads
    bda_mat         float32 [B, 4, 4]          BEV-augmentation matrix          the key sweep, index 0)
    depth_logits    float32 [B*N, D, h, w]     depth-bin logits (softmax over D gives probabilities)
    context         float32 [B*N, C_ctx, h, w] context features
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from sgde_plugin import __version__
from sgde_plugin.adapters import PriorDepthNet
from sgde_plugin.adapters.bevdepth import _depth_net_part
from sgde_plugin.errors import InputError
from sgde_plugin.geometry import camera_mount
from sgde_plugin.nn import DepthNet
from sgde_plugin.nn.encoding import LOG_FLOOR_M, LOG_REFERENCE_M

R18_INPUTS = ("image", "prior")
R18_OUTPUTS = ("depth",)
BEVDEPTH_INPUTS = ("features", "prior", "intrin_mats", "ida_mats", "sensor2ego_mats", "bda_mat")
BEVDEPTH_OUTPUTS = ("depth_logits", "context")
R18_DEFAULT_SIZE = (384, 640)
BEVDEPTH_DEFAULT_SIZE = (256, 704)  # image size; features at stride 16: 16 x 44
BEVDEPTH_DEFAULTS = {"in_channels": 512, "mid_channels": 512, "context_channels": 80, "depth_channels": 112}
DEFORM_OPSET = 19  # the first opset with DeformConv
NUSCENES_YAWS_DEG = (0.0, -55.0, -110.0, 180.0, 110.0, 55.0)


class R18ForExport(nn.Module):
    """``sgde_plugin.nn.DepthNet`` with a single-tensor output: (image, prior) -> depth."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: Tensor, prior: Tensor) -> Tensor:
        """[B,3,H,W] RGB in [0,1], [B,1,H,W] metres -> [B,1,H,W] metres."""
        return self.net.predict(image, prior)


class BEVDepthForExport(nn.Module):
    """``PriorDepthNet`` with positional tensor inputs and its output split into logits and context."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(
        self, features: Tensor, prior: Tensor, intrin_mats: Tensor, ida_mats: Tensor,
        sensor2ego_mats: Tensor, bda_mat: Tensor,
    ) -> tuple[Tensor, Tensor]:
        """See the module docstring for shapes."""
        mats = {"intrin_mats": intrin_mats, "ida_mats": ida_mats, "sensor2ego_mats": sensor2ego_mats,
                "bda_mat": bda_mat}
        out = self.net(features, mats, prior=prior)
        d = self.net.depth_channels
        return out[:, :d], out[:, d:]


@dataclass
class ExportSpec:
    """Everything needed to export and check one model: module, names, axes, metadata, input makers."""

    name: str
    module: nn.Module
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    dynamic_axes: dict[str, dict[int, str]]
    metadata: dict[str, str]
    random_inputs: Callable[[int, int], tuple[Tensor, ...]]  # (batch, seed) -> inputs
    synthetic_inputs: Callable[[int], tuple[str, tuple[Tensor, ...]]]  # batch -> (source label, inputs)
    extra: dict[str, Any] = field(default_factory=dict)


def state_dict_sha256(module: nn.Module) -> str:
    """SHA-256 of a module's parameters and buffers (names, shapes, float32 bytes), for provenance."""
    h = hashlib.sha256()
    for key, value in sorted(module.state_dict().items()):
        h.update(key.encode())
        h.update(str(tuple(value.shape)).encode())
        h.update(value.detach().to(torch.float32).contiguous().numpy().tobytes() if value.is_floating_point()
                 else value.detach().contiguous().numpy().tobytes())
    return h.hexdigest()


def load_checkpoint(path: str | Path) -> tuple[dict[str, Tensor], dict[str, Any]]:
    """Read a checkpoint with ``torch.load(weights_only=True)`` -> (state dict, info).

    Accepts a bare state dict or a dict with ``state_dict``/``model`` plus optional ``config``
    (constructor keywords) and ``fingerprint`` (the training data fingerprint). Bad files raise
    InputError naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, None, "checkpoint file not found")
    try:
        with warnings.catch_warnings():  # torch warns about a file's pickle protocol before refusing it
            warnings.simplefilter("ignore", UserWarning)
            obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad input file
        first = (str(exc).strip().splitlines() or [""])[0][:200]  # torch's explanation runs over many lines
        raise InputError(path, None, f"not a weights-only torch checkpoint ({type(exc).__name__}: {first})") from None
    if not isinstance(obj, dict):
        raise InputError(path, None, f"expected a dict, found {type(obj).__name__}")
    info: dict[str, Any] = {}
    state = obj
    for key in ("state_dict", "model"):
        if isinstance(obj.get(key), dict):
            state = obj[key]
            info = {k: v for k, v in obj.items() if k != key}
            break
    if not state or not all(isinstance(v, Tensor) for v in state.values()):
        raise InputError(path, "state_dict", "missing, empty or holding non-tensor values")
    if "config" in info and not isinstance(info["config"], dict):
        raise InputError(path, "config", "must be a dict of constructor keywords")
    return state, info


def _load_into(module: nn.Module, state: dict[str, Tensor], path: str | Path) -> None:
    try:
        missing, unexpected = module.load_state_dict(state, strict=False)
    except RuntimeError as exc:  # shape mismatches
        detail = " ".join(line.strip() for line in str(exc).splitlines()[1:3])
        raise InputError(path, "state_dict", f"does not fit the model: {detail}") from None
    if missing or unexpected:
        raise InputError(path, "state_dict", f"does not fit the model (missing {list(missing)[:3]}, "
                         f"unexpected {list(unexpected)[:3]})")


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _sparse_prior(shape: tuple[int, ...], g: torch.Generator, max_depth: float, fill: float = 0.3) -> Tensor:
    """Random prior: positive metres on about ``fill`` of the pixels, 0 elsewhere."""
    depth = 1.0 + torch.rand(shape, generator=g) * (max_depth - 1.0)
    keep = torch.rand(shape, generator=g) < fill
    return torch.where(keep, depth, torch.zeros_like(depth))


RENDER_SCALE = 0.11  # nuScenes preset at 176 x 99 pixels: a few seconds of ray casting


@functools.lru_cache(maxsize=2)
def rendered_frame(seed: int = 0, scale: float = RENDER_SCALE) -> tuple[Tensor, Tensor] | None:
    """One frame of the synthetic nuScenes-like rig: RGB [6, 3, h, w] in [0, 1] and depth [6, h, w] (m, 0 = none).

    Rendered with ``sgde_plugin.synth`` (cached per process); None when that renderer is unavailable.
    """
    try:
        from sgde_plugin.synth.sequence import synth_sequence
    except ImportError:
        return None
    seq = synth_sequence("nuscenes", frames=1, seed=seed, scale=scale)
    fid = sorted(seq.images)[0]
    names = [c.name for c in seq.rig_true.cameras]
    rgb = torch.stack([torch.from_numpy(seq.images[fid][n]).permute(2, 0, 1).float() / 255.0 for n in names])
    depth = torch.stack([torch.from_numpy(seq.depths[fid][n]).float() for n in names])
    return rgb, depth


def _overlap_band_prior(depth: Tensor, fraction: float = 0.2) -> Tensor:
    """Stand-in prior: the depth in the outer ``fraction`` of columns (where ring neighbours overlap), else 0."""
    w = depth.shape[-1]
    cols = torch.arange(w)
    band = (cols < fraction * w) | (cols >= (1 - fraction) * w)
    return torch.where(band, depth, torch.zeros_like(depth))


def _rendered_cameras(batch_images: int) -> tuple[Tensor, Tensor] | None:
    """``batch_images`` camera images of the rendered frame (cycling through its six cameras) and their depths."""
    frame = rendered_frame()
    if frame is None:
        return None
    rgb, depth = frame
    idx = torch.arange(batch_images) % rgb.shape[0]
    return rgb[idx], depth[idx]


def generated_image_and_prior(batch: int, height: int, width: int, cams: int = 1) -> tuple[Tensor, Tensor]:
    """A deterministic generated frame (not a render): textured RGB in [0, 1] and a ground-plane prior.

    The prior is the depth of a flat ground seen by a level camera 1.5 m high (focal = width / 2),
    present only in the outer 20 % columns of each image, where neighbouring views overlap in a ring.
    Shapes: [batch*cams, 3, H, W] and [batch*cams, 1, H, W].
    """
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32),
                          indexing="ij")
    frames, priors = [], []
    for k in range(batch * cams):
        phase = 0.7 * k
        r = 0.5 + 0.35 * torch.sin(u / 9.0 + phase) * torch.cos(v / 13.0)
        gch = 0.5 + 0.3 * torch.sin((u + v) / 17.0 - phase)
        bch = ((torch.floor(u / 16) + torch.floor(v / 16)) % 2) * 0.6 + 0.2
        frames.append(torch.stack([r, gch, bch]).clamp(0, 1))
        f, cy, cam_h = width / 2.0, (height - 1) / 2.0, 1.5
        below = v > cy + 1.0
        ground = torch.where(below, f * cam_h / torch.clamp(v - cy, min=1.0), torch.zeros_like(v))
        band = (u < 0.2 * width) | (u >= 0.8 * width)
        priors.append(torch.where(band & below, ground.clamp(max=79.0), torch.zeros_like(v))[None])
    return torch.stack(frames), torch.stack(priors)


def nuscenes_like_mats(batch: int, cams: int, image_size: tuple[int, int], sweeps: int = 1) -> dict[str, Tensor]:
    """Camera matrices of a surround rig (nuScenes-like yaws, 1.6 m high) in BEVDepth's layout.

    ``intrin_mats``, ``ida_mats``, ``sensor2ego_mats`` [B, sweeps, N, 4, 4] (every sweep alike) and
    ``bda_mat`` [B, 4, 4].
    """
    h, w = image_size
    yaws = NUSCENES_YAWS_DEG if cams == len(NUSCENES_YAWS_DEG) else [360.0 * i / cams for i in range(cams)]
    K = torch.eye(4)
    K[0, 0] = K[1, 1] = 0.8 * w
    K[0, 2], K[1, 2] = (w - 1) / 2.0, (h - 1) / 2.0
    s2e = torch.stack([
        torch.as_tensor(camera_mount(math.radians(y), np.array([1.0, 0.0, 1.6])), dtype=torch.float32)
        for y in yaws
    ])
    ida = torch.eye(4)
    ida[0, 0] = ida[1, 1] = 0.44
    ida[1, 3] = -140.0
    return {
        "intrin_mats": K.expand(batch, sweeps, cams, 4, 4).clone(),
        "ida_mats": ida.expand(batch, sweeps, cams, 4, 4).clone(),
        "sensor2ego_mats": s2e.expand(batch, sweeps, cams, 4, 4).clone(),
        "bda_mat": torch.eye(4).expand(batch, 4, 4).clone(),
    }


def _common_metadata(name: str, module: nn.Module, info: dict[str, Any]) -> dict[str, str]:
    fingerprint = info.get("fingerprint") or info.get("training_fingerprint") or "none (untrained weights)"
    return {
        "sgde.model": name,
        "sgde.version": __version__,
        "sgde.training_fingerprint": str(fingerprint),
        "sgde.weights_sha256": state_dict_sha256(module),
    }


def build_r18(checkpoint: str | Path | None = None, image_size: tuple[int, int] = R18_DEFAULT_SIZE) -> ExportSpec:
    """The R18 reference depth net (``sgde_plugin.nn.DepthNet``) ready for export."""
    state, info = load_checkpoint(checkpoint) if checkpoint is not None else (None, {})
    config = dict(info.get("config", {}))
    config.setdefault("use_prior", True)
    if not config["use_prior"]:
        raise InputError(checkpoint, "config.use_prior", "the exported R18 net takes a prior; got use_prior=False")
    try:
        net = DepthNet(**config)
    except (TypeError, ValueError) as exc:
        raise InputError(checkpoint, "config", str(exc)) from None
    if state is not None:
        _load_into(net, state, checkpoint)
    net.eval()
    h, w = image_size
    if h % 32 or w % 32:
        raise InputError(None, "--image-size", f"{h}x{w}: height and width must be multiples of 32")
    prior_max = net.encoding.max_depth
    validity = net.encoding.with_validity
    scheme = (f"log(clip(prior_m, {LOG_FLOOR_M:g}, max_depth) / {LOG_REFERENCE_M:g}); 0 = no prior (and 10 m: "
              "see the validity channel)"
              if net.encoding.form == "log" else "clip(prior_m / max_depth, 0, 1); 0 = no prior")
    module = R18ForExport(net).eval()

    def random_inputs(batch: int, seed: int) -> tuple[Tensor, Tensor]:
        g = _generator(seed)
        return torch.rand(batch, 3, h, w, generator=g), _sparse_prior((batch, 1, h, w), g, prior_max)

    def synthetic_inputs(batch: int) -> tuple[str, tuple[Tensor, Tensor]]:
        cams = _rendered_cameras(batch)
        if cams is None:
            return "generated", generated_image_and_prior(batch, h, w)
        rgb, depth = cams
        ch, cw = (rgb.shape[-2] // 32) * 32, (rgb.shape[-1] // 32) * 32  # the net wants multiples of 32
        rgb, depth = rgb[..., :ch, :cw], depth[..., :ch, :cw]
        return f"rendered {ch}x{cw}", (rgb.contiguous(), _overlap_band_prior(depth).unsqueeze(1).contiguous())

    metadata = _common_metadata("r18", net, info) | {
        "sgde.inputs": json.dumps({"image": "float32 [B,3,H,W] RGB in [0,1], NCHW",
                                   "prior": "float32 [B,1,H,W] metres, 0 = no prior"}),
        "sgde.outputs": json.dumps({"depth": "float32 [B,1,H,W] metres"}),
        "sgde.input_layout": "NCHW; RGB channel order; ImageNet mean/std applied inside the graph",
        "sgde.depth_range": json.dumps([net.min_depth, net.max_depth]),
        "sgde.prior_normalisation": json.dumps({"scheme": scheme, "max_depth": prior_max,
                                                "validity_channel": validity}),
        "sgde.export_image_size": json.dumps([h, w]),
    }
    axes = {"image": {0: "batch", 2: "height", 3: "width"}, "prior": {0: "batch", 2: "height", 3: "width"},
            "depth": {0: "batch", 2: "height", 3: "width"}}
    return ExportSpec("r18", module, R18_INPUTS, R18_OUTPUTS, axes, metadata, random_inputs, synthetic_inputs,
                      {"image_size": (h, w)})


def _config_from_state(state: dict[str, Tensor] | None) -> dict[str, Any]:
    """PriorDepthNet sizes read off a BEVDepth-style DepthNet state dict (empty when they cannot be)."""
    if not state or "reduce_conv.0.weight" not in state or "context_conv.weight" not in state:
        return {}
    deformable = "depth_conv.4.conv_offset.weight" in state
    last = state.get(f"depth_conv.{5 if deformable else 4}.weight")
    config = {"in_channels": int(state["reduce_conv.0.weight"].shape[1]),
              "mid_channels": int(state["reduce_conv.0.weight"].shape[0]),
              "context_channels": int(state["context_conv.weight"].shape[0]), "deformable": deformable}
    if last is not None:
        config["depth_channels"] = int(last.shape[0])
    return config


def _bevdepth_net(checkpoint: str | Path | None, overrides: dict[str, Any]) -> tuple[PriorDepthNet, dict[str, Any]]:
    """`build_bevdepth`, network: the PriorDepthNet (config from checkpoint and overrides, weights loaded), eval."""
    state, info = load_checkpoint(checkpoint) if checkpoint is not None else (None, {})
    if state is not None:
        state = dict(_depth_net_part(state))
    config = BEVDEPTH_DEFAULTS | _config_from_state(state) | dict(info.get("config", {})) | overrides
    config["use_prior"] = True
    try:
        net = PriorDepthNet(**config)
    except (TypeError, ValueError) as exc:
        raise InputError(checkpoint, "config", str(exc)) from None
    if state is not None:
        try:
            net.load_state_dict(state)  # BEVDepth key names; strict, one-line refusal
        except InputError as exc:
            raise InputError(checkpoint, exc.key, exc.problem) from None
    return net.eval(), info


def _bevdepth_metadata(
    net: PriorDepthNet, info: dict[str, Any], cams: int, image_size: tuple[int, int]
) -> dict[str, str]:
    """`build_bevdepth`, metadata: the ONNX metadata (inputs, outputs, layout, depth bins, prior encoding)."""
    h, w = image_size
    s = net.downsample
    fh, fw = h // s, w // s
    cin = net.reduce_conv[0].in_channels
    return _common_metadata("bevdepth", net, info) | {
        "sgde.inputs": json.dumps({
            "features": f"float32 [B*N,{cin},{fh},{fw}] image features at stride {s}",
            "prior": f"float32 [B,N,{h},{w}] metres at the augmented image size, 0 = no prior",
            "intrin_mats": "float32 [B,S,N,4,4] (BEVDepth mats_dict; sweep 0 is used)",
            "ida_mats": "float32 [B,S,N,4,4]", "sensor2ego_mats": "float32 [B,S,N,4,4] camera -> ego",
            "bda_mat": "float32 [B,4,4]",
        }),
        "sgde.outputs": json.dumps({
            "depth_logits": f"float32 [B*N,{net.depth_channels},{fh},{fw}] logits of the depth bins",
            "context": f"float32 [B*N,{net.context_channels},{fh},{fw}]",
        }),
        "sgde.input_layout": ("NCHW features with batch and cameras folded (b * N + n); matrices as BEVDepth's "
                              "mats_dict [B, sweeps, N, 4, 4]; one sweep per run"),
        "sgde.depth_range": json.dumps(list(net.d_bound)),
        "sgde.depth_bins": json.dumps({"d_bound": list(net.d_bound), "bins": net.depth_channels,
                                       "bin_k": "[start + k*step, start + (k+1)*step) metres"}),
        "sgde.prior_normalisation": json.dumps({
            "scheme": f"min non-zero per {s}x{s} cell, clip(prior_m / max_depth, 0, 1) + validity; 0 = none",
            "max_depth": net.prior_encoder.encoding.max_depth, "validity_channel": True}),
        "sgde.cameras_per_sample": str(cams),
    }


BEVDEPTH_AXES = {
    "features": {0: "batch_x_cams"}, "prior": {0: "batch", 1: "cams"},
    "intrin_mats": {0: "batch", 1: "sweeps", 2: "cams"}, "ida_mats": {0: "batch", 1: "sweeps", 2: "cams"},
    "sensor2ego_mats": {0: "batch", 1: "sweeps", 2: "cams"}, "bda_mat": {0: "batch"},
    "depth_logits": {0: "batch_x_cams"}, "context": {0: "batch_x_cams"},
}


def build_bevdepth(
    checkpoint: str | Path | None = None,
    image_size: tuple[int, int] = BEVDEPTH_DEFAULT_SIZE,
    cams: int = 6,
    **overrides: Any,
) -> ExportSpec:
    """The BEVDepth-style depth branch (``PriorDepthNet``) ready for export; ``overrides`` go to its constructor.

    A checkpoint may be this project's (with a ``config``) or BEVDepth's (a DepthNet state dict or a
    whole model's, ``...depth_net.*``): channels and the deformable convolution are then read off it.
    """
    net, info = _bevdepth_net(checkpoint, overrides)
    h, w = image_size
    s = net.downsample
    if h % s or w % s:
        raise InputError(None, "--image-size", f"{h}x{w}: must be multiples of the feature stride {s}")
    fh, fw = h // s, w // s
    cin = net.reduce_conv[0].in_channels
    module = BEVDepthForExport(net).eval()

    def mats_tuple(batch: int) -> tuple[Tensor, ...]:
        m = nuscenes_like_mats(batch, cams, (h, w))
        return m["intrin_mats"], m["ida_mats"], m["sensor2ego_mats"], m["bda_mat"]

    def random_inputs(batch: int, seed: int) -> tuple[Tensor, ...]:
        g = _generator(seed)
        feats = torch.randn(batch * cams, cin, fh, fw, generator=g)
        prior = _sparse_prior((batch, cams, h, w), g, net.d_bound[1], fill=0.05)
        intr, ida, s2e, bda = mats_tuple(batch)
        intr = intr.clone()
        intr[..., :2, :3] *= 1.0 + 0.05 * torch.randn(batch, 1, cams, 1, 1, generator=g)
        return feats, prior, intr, ida, s2e, bda

    def synthetic_inputs(batch: int) -> tuple[str, tuple[Tensor, ...]]:
        rendered = _rendered_cameras(batch * cams)
        if rendered is None:
            label = "generated"
            image, prior = generated_image_and_prior(batch, h, w, cams)
        else:
            label = "rendered"
            image = torch.nn.functional.interpolate(rendered[0], size=(h, w), mode="bilinear", align_corners=False)
            depth = torch.nn.functional.interpolate(rendered[1][:, None], size=(h, w), mode="nearest")
            prior = _overlap_band_prior(depth)
        # stand-in backbone: average colour per 16x16 cell, tiled over the feature channels
        cells = torch.nn.functional.avg_pool2d(image, s)
        reps = math.ceil(cin / 3)
        feats = (cells.repeat(1, reps, 1, 1)[:, :cin] - 0.5) * 4.0
        return label, (feats, prior.reshape(batch, cams, h, w), *mats_tuple(batch))

    metadata = _bevdepth_metadata(net, info, cams, (h, w))
    axes = {k: dict(v) for k, v in BEVDEPTH_AXES.items()}
    extra = {"image_size": (h, w), "feature_size": (fh, fw), "cams": cams}
    if net.deformable:
        extra["min_opset"] = DEFORM_OPSET
    return ExportSpec("bevdepth", module, BEVDEPTH_INPUTS, BEVDEPTH_OUTPUTS, axes, metadata, random_inputs,
                      synthetic_inputs, extra)


BUILDERS: dict[str, Callable[..., ExportSpec]] = {"r18": build_r18, "bevdepth": build_bevdepth}
