"""Materials of the synthetic world: view-independent albedo textures and Lambertian shading.

Colour depends only on the surface point (its texture coordinates on its own surface), the
surface normal and a fixed sun, never on the viewing direction. The pixel footprint (metres) is
only used to band-limit the texture (see `noise`), which is what a real pixel integrates.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .noise import band, fbm, stripes
from .world import CAR_BODY, CAR_GLASS, FACADE, METAL, SIDEWALK, TYRE, World

_SKY_HORIZON = torch.tensor([0.78, 0.84, 0.90])
_SKY_ZENITH = torch.tensor([0.35, 0.52, 0.80])
_PAINT = torch.tensor([0.88, 0.88, 0.84])
_GLASS = torch.tensor([0.30, 0.36, 0.44])  # window glass mostly reflects the sky
_FRAME = torch.tensor([0.85, 0.84, 0.80])
_MORTAR = torch.tensor([0.72, 0.70, 0.66])
_ROOF = torch.tensor([0.30, 0.29, 0.28])

# octave gains (7 octaves, lattice spacing texel * 2**c)
_G_FINE = torch.tensor([0.03, 0.05, 0.07, 0.11, 0.14, 0.14, 0.11])
_G_COARSE = torch.tensor([0.05, 0.06, 0.07, 0.07, 0.06, 0.05, 0.05])
_G_SOFT = torch.tensor([0.02, 0.025, 0.03, 0.03, 0.03, 0.025, 0.02])


def sky(d: Tensor) -> Tensor:
    """Sky colour by ray elevation (a plain gradient)."""
    e = d[:, 2].clamp(0, 1).sqrt()[:, None]
    return _SKY_HORIZON * (1 - e) + _SKY_ZENITH * e


def _mix(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    return a * (1 - w[:, None]) + b * w[:, None]


# texture pre-filter width in pixels: a real camera's optics and demosaicing blur over ~1.5 pixels
FILTER_PX = 1.5
# surfaces themselves carry no detail finer than this (soft paint and frame edges), in metres
SURFACE_BLUR_M = 0.015


def _footprint(q: Tensor, n: Tensor, pixel_angle: Tensor, min_cos: float = 0.5) -> Tensor:
    """Texture pre-filter width (m) of surface points at offsets `q` (n, 3) from the LOD origin, normals `n`.

    The pixel footprint at the point's distance, widened at oblique incidence (up to 1 / min_cos).
    With the LOD origin shared by a rig, every camera filters a point the same way. The ground is
    seen at nearly the same grazing angle from the whole rig, so it may widen a lot; walls are seen
    from very different directions by neighbouring cameras, so their widening is kept small.
    """
    dist = q.norm(dim=1).clamp_min(1e-6)
    cos = (q * n).sum(1).abs() / dist
    f = FILTER_PX * dist * pixel_angle / cos.clamp_min(min_cos)
    return torch.sqrt(f * f + SURFACE_BLUR_M**2)


def ground_albedo(world: World, x: Tensor, y: Tensor, f: Tensor) -> Tensor:
    """Asphalt with grain and stains, lane markings and zebra crossings; (n, 3)."""
    bank = world.noise
    grain = fbm(bank, x + 13.1, y + 7.7, f, 0.012, _G_FINE * 1.6)
    stain = fbm(bank, y * 0.97 + 51.0, x * 0.97 + 3.3, f, 0.2, _G_COARSE * 1.4)
    base = 0.30 * (1 + grain + stain)
    asphalt = base[:, None] * torch.tensor([0.96, 0.98, 1.0])
    ay = y.abs()
    centre = band(y, -0.07, 0.07, f) * stripes(x, 9.0, 3.0, f)
    lanes = band(ay, 3.45, 3.60, f) * stripes(x + 1.0, 4.0, 2.5, f)
    edge = band(ay, 5.65, 5.80, f)
    xm = torch.remainder(x + 40.0, 150.0)
    zebra = band(xm, 70.0, 74.0, f) * stripes(y + 6.0, 1.0, 0.5, f) * band(ay, 0.0, 5.5, f)
    paint = torch.maximum(torch.maximum(centre, lanes), torch.maximum(edge, zebra)) * (0.85 + 2 * grain).clamp(0, 1)
    return _mix(asphalt, _PAINT * (1 + 0.5 * grain[:, None]), paint)


def facade_albedo(world: World, s: Tensor, z: Tensor, f: Tensor, colour: Tensor, params: Tensor) -> Tensor:
    """Walls (brick or plaster) with floors of framed windows and shop windows at street level; (n, 3)."""
    bank = world.noise
    floor_h, spacing, win_w, win_h, brick, top = params.unbind(1)
    grain = fbm(bank, s, z, f, 0.01, _G_FINE)
    blotch = fbm(bank, z * 0.9 + 11.0, s * 0.9 + 5.0, f, 0.15, _G_COARSE * 1.3)
    wall = colour * (1 + grain + blotch)[:, None]
    # bricks: 7.5 cm courses, 24 cm bricks in running bond, 1 cm mortar
    row = torch.floor(z / 0.075)
    shift = torch.remainder(row, 2.0) * 0.12
    mortar = 1 - (1 - stripes(z, 0.075, 0.01, f)) * (1 - stripes(s + shift, 0.24, 0.01, f))
    wall = _mix(wall, _MORTAR * (1 + grain[:, None]), mortar * brick * 0.35)
    # a cornice line at every floor
    cornice = stripes(z - floor_h + 0.1, floor_h, 0.22, f) * band(z, floor_h - 0.5, top - 0.3, f)
    wall = _mix(wall, colour * 0.75 + 0.2, cornice * 0.8)
    # framed windows on the upper floors
    sill = (floor_h - win_h) / 2
    x0 = (spacing - win_w) / 2
    upper = band(z, floor_h, top - 0.8, f)
    frame = stripes(s - x0 + 0.12, spacing, win_w + 0.24, f) * stripes(z - sill + 0.12, floor_h, win_h + 0.24, f)
    glass = stripes(s - x0, spacing, win_w, f) * stripes(z - sill, floor_h, win_h, f)
    # shop windows at street level
    shop = band(z, 0.55, floor_h - 0.6, f) * stripes(s - 0.4, 2 * spacing, 1.5 * spacing, f)
    glass_col = _GLASS * (1 + 1.5 * blotch[:, None] + grain[:, None])
    out = _mix(wall, (0.5 * _FRAME + 0.5 * wall) * (1 + 0.5 * grain[:, None]), frame * upper)
    out = _mix(out, glass_col, torch.maximum(glass * upper, shop))
    low = torch.nonzero(z < floor_h).flatten()  # signs and posters are on the ground floor only
    if low.numel():
        out[low] = _signs(out[low], s[low], z[low], f[low], floor_h[low], spacing[low])
    return out


def hash01(i: Tensor, salt: int) -> Tensor:
    """A deterministic pseudo-random value in [0, 1) per integer (int64 tensor), for per-cell choices."""
    h = (i * 0x9E3779B1 + salt * 0x85EBCA77) & 0xFFFFFFFF
    h = h ^ (h >> 15)
    h = (h * 0x2C1B3C6D) & 0xFFFFFFFF
    h = h ^ (h >> 12)
    h = (h * 0x297A2D39) & 0xFFFFFFFF
    h = h ^ (h >> 15)
    return h.to(torch.float32) / 4294967296.0


def _signs(out: Tensor, s: Tensor, z: Tensor, f: Tensor, floor_h: Tensor, spacing: Tensor) -> Tensor:
    """Shop signs with letter-like blocks above the shop windows and posters between them (distinct features)."""
    # one sign panel per shop-window bay, in the band just below the first cornice
    bay = torch.floor((s - 0.4) / (2 * spacing)).to(torch.int64)
    present = (hash01(bay, 1) < 0.7).float()
    panel = band(z, floor_h - 0.58, floor_h - 0.18, f) * stripes(s - 0.5, 2 * spacing, 1.3 * spacing, f) * present
    hue = torch.stack([hash01(bay, 2), hash01(bay, 3), hash01(bay, 4)], dim=1)
    back = 0.15 + 0.8 * hue
    ink = 1.0 - back
    letter = torch.floor(s / 0.26).to(torch.int64)
    glyph = (hash01(letter, 5) < 0.75).float() * stripes(s, 0.26, 0.17, f) * band(z, floor_h - 0.50, floor_h - 0.26, f)
    sign = _mix(back, ink, glyph)
    out = _mix(out, sign, panel)
    # posters on the wall between the shop windows
    cell = torch.floor((s - 0.4 - 1.55 * spacing) / (2 * spacing)).to(torch.int64)
    has = (hash01(cell, 6) < 0.5).float()
    poster = band(z, 0.9, 2.1, f) * stripes(s - 0.4 - 1.55 * spacing, 2 * spacing, 0.4 * spacing, f) * has
    pcol = torch.stack([hash01(cell, 7), hash01(cell, 8), hash01(cell, 9)], dim=1)
    rows = stripes(z, 0.3, 0.14, f)[:, None]
    art = pcol * (1 - rows) + (1 - pcol) * rows * 0.8
    return _mix(out, art, poster)


def car_albedo(world: World, s: Tensor, z: Tensor, f: Tensor, colour: Tensor, material: Tensor,
               top: Tensor) -> Tensor:
    """Car paint with door seams and a trim line, tinted glass on the cabin sides, dark tyres; (n, 3)."""
    bank = world.noise
    grain = fbm(bank, s + 3.0, z + 1.0, f, 0.01, _G_SOFT * 2)
    paint = colour * (1 + grain[:, None] + 0.6 * fbm(bank, z, s, f, 0.08, _G_SOFT)[:, None])
    seams = stripes(s + 0.45, 1.05, 0.02, f) * band(z, 0.35, 0.95, f)
    trim = band(torch.remainder(z, 10.0), 0.62, 0.68, f)
    body = _mix(paint, paint * 0.35, torch.maximum(seams, trim))
    glass_col = _GLASS * 0.5 * (1 + 3 * fbm(bank, s * 0.5 + 9.0, z, f, 0.05, _G_COARSE)[:, None])
    pillars = stripes(s + 0.1, 0.9, 0.12, f)
    cabin = _mix(glass_col, paint, pillars)
    cabin = torch.where(top[:, None], paint, cabin)
    tyre = torch.tensor([0.07, 0.07, 0.075]) * (1 + 2 * grain[:, None])
    out = torch.where((material == CAR_GLASS)[:, None], cabin, body)
    return torch.where((material == TYRE)[:, None], tyre, out)


def sidewalk_albedo(world: World, x: Tensor, y: Tensor, f: Tensor, top: Tensor) -> Tensor:
    """Paving slabs with joints on top, concrete curb faces; (n, 3)."""
    bank = world.noise
    grain = fbm(bank, x + 71.0, y + 17.0, f, 0.01, _G_FINE * 1.3)
    blotch = fbm(bank, y + 5.0, x + 2.0, f, 0.12, _G_COARSE)
    slab = torch.tensor([0.62, 0.60, 0.56]) * (1 + grain + blotch)[:, None]
    joints = 1 - (1 - stripes(x, 0.6, 0.012, f)) * (1 - stripes(y, 0.6, 0.012, f))
    slab = _mix(slab, slab * 0.55, joints)
    curb = torch.tensor([0.70, 0.69, 0.66]) * (1 + grain + blotch)[:, None]
    return torch.where(top[:, None], slab, curb)


def metal_albedo(world: World, s: Tensor, z: Tensor, f: Tensor, colour: Tensor) -> Tensor:
    """Painted metal with rust streaks and bands (poles, lamp arms); (n, 3)."""
    bank = world.noise
    grain = fbm(bank, s * 3.0 + 1.0, z + 40.0, f, 0.01, _G_FINE)
    bands = stripes(z, 1.3, 0.08, f)
    return _mix(colour * (1 + grain[:, None]), colour * 0.5, bands)


def _light(world: World, n: Tensor) -> Tensor:
    sun = torch.from_numpy(world.sun).float()
    return 0.55 + 0.1 * n[:, 2] + 0.45 * (n @ sun).clamp_min(0)


def shade(world: World, t: Tensor, pid: Tensor, dirs: Tensor, pixel_angle: Tensor, valid: Tensor,
          origin: np.ndarray, time_s: float, lod_origin: np.ndarray | None = None) -> Tensor:
    """Linear RGB in [0, 1] of every ray (same leading shape as `t`) from the hits of `trace`.

    Rays start at `origin` (world); texture level of detail is measured from `lod_origin`
    (world, default `origin`).
    """
    off = np.zeros(3) if lod_origin is None else np.asarray(origin, np.float64) - np.asarray(lod_origin, np.float64)
    lod_off = torch.from_numpy(off).float()
    shape = t.shape
    t, pid, d = t.reshape(-1), pid.reshape(-1), dirs.reshape(-1, 3)
    pa, valid = pixel_angle.reshape(-1), valid.reshape(-1)
    out = sky(d)
    out[~valid] = 0.0

    # ground
    g = torch.nonzero(pid == 0).flatten()
    if g.numel():
        tg, dg = t[g], d[g]
        x = float(origin[0]) + tg * dg[:, 0]
        y = float(origin[1]) + tg * dg[:, 1]
        n = torch.tensor([[0.0, 0.0, 1.0]]).expand(g.numel(), 3)
        f = _footprint(lod_off + tg[:, None] * dg, n, pa[g], min_cos=0.15)
        out[g] = ground_albedo(world, x, y, f) * _light(world, n)[:, None]

    # boxes
    b = torch.nonzero((pid >= 1) & (pid <= world.n_boxes)).flatten()
    if b.numel():
        out[b] = _shade_boxes(world, t[b], pid[b] - 1, d[b], pa[b], origin, time_s, lod_off)

    # poles
    p = torch.nonzero(pid > world.n_boxes).flatten()
    if p.numel():
        m = (pid[p] - 1 - world.n_boxes).long()
        tp, dp = t[p], d[p]
        cxy = torch.from_numpy(world.pole_xy - origin[:2]).float()[m]
        hx, hy = tp * dp[:, 0] - cxy[:, 0], tp * dp[:, 1] - cxy[:, 1]
        r = torch.from_numpy(world.pole_radius).float()[m]
        n = torch.stack([hx / r, hy / r, torch.zeros_like(hx)], dim=1)
        z = float(origin[2]) + tp * dp[:, 2]
        s = torch.atan2(hy, hx) * r
        f = _footprint(lod_off + tp[:, None] * dp, n, pa[p])
        colour = torch.from_numpy(world.pole_color).float()[m]
        out[p] = metal_albedo(world, s, z, f, colour) * _light(world, n)[:, None]
    return out.reshape(*shape, 3)


def _box_table(world: World, origin: np.ndarray, time_s: float) -> Tensor:
    """Per-box float parameters packed for one gather: (N, 22).

    Columns: camera origin in the box frame (0:3), cos/sin of -yaw (3:5), half sizes (5:8), centre
    (8:11), texture offsets (11:13), colour (13:16), material params (16:22).
    """
    centers = world.box_centers(time_s)
    c, s_ = np.cos(-world.box_yaw), np.sin(-world.box_yaw)
    rel = origin[None, :] - centers
    o_loc = np.stack([c * rel[:, 0] - s_ * rel[:, 1], s_ * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1)
    table = np.concatenate([o_loc, c[:, None], s_[:, None], world.box_half, centers, world.box_tex_offset,
                            world.box_color, world.box_params], axis=1)
    return torch.from_numpy(table).float()


def _shade_boxes(world: World, t: Tensor, j: Tensor, d: Tensor, pa: Tensor, origin: np.ndarray,
                 time_s: float, lod_off: Tensor) -> Tensor:
    j = j.long()
    q = _box_table(world, origin, time_s)[j]
    cj, sj = q[:, 3], q[:, 4]
    dl = torch.stack([cj * d[:, 0] - sj * d[:, 1], sj * d[:, 0] + cj * d[:, 1], d[:, 2]], dim=1)
    p = q[:, 0:3] + t[:, None] * dl
    face = (p.abs() - q[:, 5:8]).argmax(dim=1)
    sign = torch.sign(p.gather(1, face[:, None]))[:, 0]
    n_loc = torch.zeros_like(p).scatter_(1, face[:, None], sign[:, None])
    n = torch.stack([cj * n_loc[:, 0] + sj * n_loc[:, 1], -sj * n_loc[:, 0] + cj * n_loc[:, 1], n_loc[:, 2]], dim=1)
    f = _footprint(lod_off + t[:, None] * d, n, pa)
    zw = p[:, 2] + q[:, 10]  # height above the ground
    top = face == 2
    s_coord = torch.where(face == 0, p[:, 1], p[:, 0]) + q[:, 11]
    v_coord = torch.where(top, p[:, 1] + q[:, 12], zw)
    material = torch.from_numpy(world.box_material)[j]
    colour = q[:, 13:16]
    albedo = torch.empty_like(p)

    is_facade = material == FACADE
    sel = torch.nonzero(is_facade & ~top).flatten()
    if sel.numel():
        albedo[sel] = facade_albedo(world, s_coord[sel], v_coord[sel], f[sel], colour[sel], q[sel, 16:22])
    sel = torch.nonzero(is_facade & top).flatten()
    if sel.numel():
        albedo[sel] = _ROOF * (1 + fbm(world.noise, s_coord[sel], v_coord[sel], f[sel], 0.02, _G_FINE)[:, None])
    sel = torch.nonzero((material == CAR_BODY) | (material == CAR_GLASS) | (material == TYRE)).flatten()
    if sel.numel():
        albedo[sel] = car_albedo(world, s_coord[sel], v_coord[sel], f[sel], colour[sel], material[sel], top[sel])
    sel = torch.nonzero(material == SIDEWALK).flatten()
    if sel.numel():
        # slabs are anchored to the world so joints run on across segments
        cx, cy = q[sel, 8], q[sel, 9]
        xs = torch.where(top[sel], p[sel, 0] + cx, s_coord[sel] + cx)
        ys = torch.where(top[sel], p[sel, 1] + cy, zw[sel])
        albedo[sel] = sidewalk_albedo(world, xs, ys, f[sel], top[sel])
    sel = torch.nonzero(material == METAL).flatten()
    if sel.numel():
        albedo[sel] = metal_albedo(world, s_coord[sel], v_coord[sel], f[sel], colour[sel])
    return albedo * _light(world, n)[:, None]
