"""Rendering: analytic ray casting of a :class:`~training.synth.scene.Scene` and its anti-aliased colour.

Rays are ``D = R_cw @ K^-1 [u, v, 1]``, so the ray parameter of a hit *is* its z-depth.
Geometry is cast at the output pixel centres in float64; colour on a 2x2 supersampled
grid in float32, then area-downsampled.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from training.synth.scene import (
    BOX0,
    DASH_LEN,
    DASH_PERIOD,
    GROUND,
    MARKINGS,
    NEAR,
    ROAD_HALF,
    SIDEWALK_OUT,
    SKY,
    Scene,
)
from training.synth.textures import M_ASPHALT, M_GRASS, M_SIDEWALK, M_SKY, SKY_REPEATS, TEXEL_M, TILE, sample_atlas

PSF_SIGMA = 0.5  # Gaussian optical blur, output pixels (applied before the 2x2 area downsample)
f32 = np.float32


def _flat(a: np.ndarray) -> np.ndarray:
    """Writable 1-D view of a contiguous array (surfaces fill their pixels by flat index)."""
    return a.reshape(-1)


@dataclass
class _Surface:
    """Texture lookup inputs per supersampled pixel, filled surface by surface (ground, sky, boxes)."""

    mat: np.ndarray  # (h, w) float32 material index
    ta: np.ndarray  # (h, w) float32 texel coordinates at mip level 0
    tb: np.ndarray
    lod: np.ndarray  # (h, w) float32 mip level
    shade: np.ndarray  # (h, w) float32 Lambert + ambient
    tint: np.ndarray  # (h, w, 3) float32 per-object tint

    @classmethod
    def empty(cls, h: int, w: int) -> _Surface:
        zeros = [np.zeros((h, w), np.float32) for _ in range(4)]
        return cls(*zeros, np.ones((h, w), np.float32), np.ones((h, w, 3), np.float32))


@dataclass
class _GroundFootprint:
    """Ground samples (flat indices) and what the lane markings need of them."""

    index: np.ndarray
    abs_d: np.ndarray  # |lateral road coordinate|, metres
    z: np.ndarray  # world z
    w_across: np.ndarray  # pixel footprint across / along the road, metres
    w_along: np.ndarray


class Renderer:
    """Ray-casts one scene on the output grid (scale 1, float64) and a supersampled grid (float32)."""

    def __init__(self, scene: Scene, supersample: int = 2):
        self.scene = scene
        self.ss = supersample
        K = scene.K
        self.grids = {}
        for s, dt in ((1, np.float64), (supersample, np.float32)):
            # Sub-pixel centres of an s x s split of each pixel: u = (j + 0.5) / s - 0.5.
            u = (np.arange(scene.width * s) + 0.5) / s - 0.5
            v = (np.arange(scene.height * s) + 0.5) / s - 0.5
            self.grids[s] = (((u - K[0, 2]) / K[0, 0]).astype(dt), ((v - K[1, 2]) / K[1, 1]).astype(dt))

    # -- geometry
    def box_rects(self, centre: np.ndarray, yaw: np.ndarray, T_wc: np.ndarray, s: int) -> np.ndarray:
        """Image rectangles (B, 4) = (row0, row1, col0, col1) on the s-grid that may see each box.

        Corners in front of the near plane plus the box edges' crossings of it bound
        the visible part; their projections bound its image. Empty rect = culled.
        """
        B = len(centre)
        if B == 0:
            return np.zeros((0, 4), np.int64)
        K, H, W = self.scene.K, self.scene.height * s, self.scene.width * s
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
        local = signs[None] * self.scene.box_half[:, None, :]  # (B, 8, 3)
        c, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        wx = c * local[..., 0] + sn * local[..., 2] + centre[:, None, 0]
        wz = -sn * local[..., 0] + c * local[..., 2] + centre[:, None, 2]
        world = np.stack([wx, local[..., 1] + centre[:, None, 1], wz], -1)
        cam = (world - T_wc[:3, 3]) @ T_wc[:3, :3]  # R^T (X - C) as row vectors
        # 12 edges: corner pairs differing in one sign bit.
        edges = np.array([(i, i | b) for b in (1, 2, 4) for i in range(8) if not i & b])
        a, b = cam[:, edges[:, 0]], cam[:, edges[:, 1]]
        za, zb = a[..., 2], b[..., 2]
        cross = (za - NEAR) * (zb - NEAR) < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            f = np.where(cross, (NEAR - za) / (zb - za), 0.0)
        pts = np.concatenate([cam, a + f[..., None] * (b - a)], axis=1)  # (B, 20, 3)
        ok = np.concatenate([cam[..., 2] >= NEAR, cross], axis=1)
        z = np.where(ok, pts[..., 2], 1.0)
        u = (K[0, 0] * pts[..., 0] / z + K[0, 2] + 0.5) * s - 0.5
        v = (K[1, 1] * pts[..., 1] / z + K[1, 2] + 0.5) * s - 0.5
        big = 1e9
        umin = np.where(ok, u, big).min(1)
        umax = np.where(ok, u, -big).max(1)
        vmin = np.where(ok, v, big).min(1)
        vmax = np.where(ok, v, -big).max(1)
        rect = np.stack([np.floor(vmin) - 1, np.ceil(vmax) + 2, np.floor(umin) - 1, np.ceil(umax) + 2], 1)
        rect = np.clip(np.nan_to_num(rect, nan=0.0, posinf=big, neginf=-big), 0, [H, H, W, W]).astype(np.int64)
        empty = ~ok.any(1) | (rect[:, 1] <= rect[:, 0]) | (rect[:, 3] <= rect[:, 2])
        rect[empty] = 0
        return rect

    def ray_dirs(self, T_wc: np.ndarray, s: int):
        """World ray directions on the s-grid: three (h, w) arrays, D = R_cw [x, y, 1] (z-depth = ray parameter)."""
        xs, ys = self.grids[s]
        R = T_wc[:3, :3].astype(xs.dtype)
        return [(R[i, 0] * xs + R[i, 2])[None, :] + (R[i, 1] * ys)[:, None] for i in range(3)]

    def cast(self, t_idx: int, s: int, boxes=None):
        """Nearest hit per ray of frame t_idx on the s-grid.

        Returns:
            depth: (h, w) z-depth (float64 for s=1, float32 otherwise), id: (h, w) int32,
            D: world ray directions (3 arrays).
        """
        sc = self.scene
        T = sc.T_wc[t_idx]
        xs, ys = self.grids[s]
        dt = xs.dtype.type
        C = T[:3, 3]
        D = self.ray_dirs(T, s)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            tg = np.where(D[1] > 1e-9, (-C[1]) / D[1], np.inf).astype(dt)  # ground plane y = 0
            o = (C - sc.sky_centre).astype(dt)
            b = o[0] * D[0] + o[1] * D[1] + o[2] * D[2]
            a = D[0] * D[0] + D[1] * D[1] + D[2] * D[2]
            c = dt(o @ o - sc.sky_radius**2)
            tsky = (-b + np.sqrt(b * b - a * c)) / a  # camera is inside the sphere: far root
            depth = np.minimum(tg, tsky)
            ids = np.where(tg < tsky, GROUND, SKY).astype(np.int32)
            centre, yaw = boxes if boxes is not None else sc.boxes_at(t_idx)
            rects = self.box_rects(centre, yaw, T, s)
            vis = np.flatnonzero(rects[:, 1] > rects[:, 0])
            # Per box: M = R_y(yaw)^T R_cw maps camera rays into the box frame, ol = camera centre there.
            cy_, sy_ = np.cos(yaw[vis]), np.sin(yaw[vis])
            RbT = np.zeros((len(vis), 3, 3))
            RbT[:, 0, 0], RbT[:, 0, 2], RbT[:, 1, 1], RbT[:, 2, 0], RbT[:, 2, 2] = cy_, -sy_, 1.0, sy_, cy_
            M = (RbT @ T[:3, :3]).tolist()
            ol = np.einsum("nij,nj->ni", RbT, C - centre[vis])
            e = sc.box_half[vis]
            slab_lo, slab_hi = (-e - ol).tolist(), (e - ol).tolist()
            for j, k in enumerate(vis):
                r0, r1, c0, c1 = rects[k]
                xsl, ysl = xs[c0:c1], ys[r0:r1]
                tn = tf = None
                for ax in range(3):
                    m0, m1, m2 = M[j][ax]
                    inv = 1 / ((dt(m0) * xsl + dt(m2))[None, :] + (dt(m1) * ysl)[:, None])
                    t1 = inv * dt(slab_lo[j][ax])
                    t2 = inv * dt(slab_hi[j][ax])
                    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
                    tn = lo if tn is None else np.maximum(tn, lo, out=tn)
                    tf = hi if tf is None else np.minimum(tf, hi, out=tf)
                dv = depth[r0:r1, c0:c1]
                hit = (tn <= tf) & (tn > 0) & (tn < dv)
                dv[hit] = tn[hit]
                ids[r0:r1, c0:c1][hit] = BOX0 + k
        return depth, ids, D

    # -- appearance
    # -- appearance
    def colour(self, t_idx: int) -> np.ndarray:
        """Anti-aliased RGB of frame t_idx: (H, W, 3) uint8."""
        sc = self.scene
        s = self.ss
        centre, yaw = sc.boxes_at(t_idx)
        depth, ids, D = self.cast(t_idx, s, (centre, yaw))
        C = sc.T_wc[t_idx, :3, 3].astype(np.float32)
        P = [C[i] + depth * D[i] for i in range(3)]
        surf = _Surface.empty(*depth.shape)
        ids_f = _flat(ids)
        fpix = f32(min(sc.K[0, 0], sc.K[1, 1]) * s)  # pixels per unit tan-angle on this grid
        ground = self._ground(surf, np.flatnonzero(ids_f == GROUND), P, depth, f32(-C[1]), fpix)
        self._sky(surf, np.flatnonzero(ids_f == SKY), P, fpix)
        bi = np.flatnonzero(ids_f >= BOX0)
        if len(bi):
            self._boxes(surf, bi, ids_f[bi] - BOX0, centre, yaw, P, D, depth, fpix)

        rgba = sample_atlas(sc.atlas, sc.atlas_y0, surf.mat, surf.ta, surf.tb, surf.lod)
        alpha = rgba[..., 3:4]
        rgb = rgba[..., :3] * (1 + alpha * (surf.tint - 1)) * surf.shade[..., None]
        if len(ground.index):
            _paint_markings(rgb, surf.shade, ground)
        if PSF_SIGMA > 0:  # camera optics: real lenses do not give 1-pixel-sharp edges
            rgb = cv2.GaussianBlur(rgb, (0, 0), PSF_SIGMA * s)
        rgb = cv2.resize(rgb, (sc.width, sc.height), interpolation=cv2.INTER_AREA) * f32(sc.gain)
        return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)

    def _ground(self, surf: _Surface, g: np.ndarray, P, depth: np.ndarray, cam_h, fpix) -> _GroundFootprint:
        """Ground: material by lateral road coordinate (markings are painted after the lookup)."""
        sc = self.scene
        gx, gz, gt = _flat(P[0])[g], _flat(P[2])[g], _flat(depth)[g]
        d = gx - sc.road.centre_f32(gz)
        ad = np.abs(d)
        gm = np.where(ad < ROAD_HALF, M_ASPHALT, np.where(ad < SIDEWALK_OUT, M_SIDEWALK, M_GRASS)).astype(np.float32)
        w_across = gt / fpix
        w_along = gt * gt / (fpix * cam_h)
        foot = np.maximum(w_across, w_along)
        inv_texel = (1 / TEXEL_M)[gm.astype(np.int32)]
        _flat(surf.mat)[g] = gm
        _flat(surf.ta)[g] = d * inv_texel
        _flat(surf.tb)[g] = gz * inv_texel
        _flat(surf.lod)[g] = np.log2(np.maximum(foot * inv_texel, 1e-6))
        _flat(surf.shade)[g] = sc.ambient + (1 - sc.ambient) * max(0.0, -sc.sun[1])
        return _GroundFootprint(g, ad, gz, w_across, w_along)

    def _sky(self, surf: _Surface, k: np.ndarray, P, fpix) -> None:
        """Sky: direction from the sphere centre -> (azimuth, elevation) texel coordinates."""
        sc = self.scene
        sx = _flat(P[0])[k] - f32(sc.sky_centre[0])
        sy = _flat(P[1])[k] - f32(sc.sky_centre[1])
        sz = _flat(P[2])[k] - f32(sc.sky_centre[2])
        az = np.arctan2(sx, sz)
        el = np.arcsin(np.clip(-sy / f32(sc.sky_radius), -1, 1))
        texels_per_rad = f32(SKY_REPEATS * TILE / (2 * np.pi))
        _flat(surf.mat)[k] = M_SKY
        _flat(surf.ta)[k] = az * texels_per_rad
        _flat(surf.tb)[k] = el * texels_per_rad
        _flat(surf.lod)[k] = np.log2(texels_per_rad / fpix)
        _flat(surf.shade)[k] = 1.0 + 0.25 * (1 - np.clip(el / 0.35, 0, 1))  # brighter towards the horizon

    def _boxes(self, surf: _Surface, bi: np.ndarray, box: np.ndarray, centre, yaw, P, D, depth, fpix) -> None:
        """Boxes: hit point in the box frame -> face, normal, face texture coordinates, shading."""
        sc = self.scene
        # One row gather of a per-box float32 table (np.take) is much cheaper than one per field.
        table = np.concatenate(
            [
                centre,
                np.cos(yaw)[:, None],
                np.sin(yaw)[:, None],
                sc.box_half,
                sc.box_texoff,
                (1 / TEXEL_M)[sc.box_mat][:, None],
                sc.box_mat[:, None],
                sc.box_tint,
            ],
            axis=1,
        ).astype(np.float32)
        cx_, cy0, cz_, cy_, sy_, ex, ey, ez, offa, offb, inv_texel, bm, tr, tg_, tbl = np.take(table, box, axis=0).T
        px, py, pz = _flat(P[0])[bi] - cx_, _flat(P[1])[bi] - cy0, _flat(P[2])[bi] - cz_
        lx = cy_ * px - sy_ * pz  # R_y(yaw)^T (P - c)
        lz = sy_ * px + cy_ * pz
        qx, qy, qz = np.abs(lx) / ex, np.abs(py) / ey, np.abs(lz) / ez
        on_x = (qx >= qy) & (qx >= qz)  # which face was hit: the largest normalised coordinate
        on_y = ~on_x & (qy >= qz)
        on_z = ~on_x & ~on_y
        # Face coordinates: horizontal along the face from its corner, vertical = height above the bottom.
        a_ = np.where(on_x, lz + ez, lx + ex)
        b_ = np.where(on_y, lz + ez, ey - py)
        # World normal of the face (local axis, sign from the side hit, rotated by yaw).
        nl = np.sign(np.where(on_x, lx, np.where(on_y, py, lz)))
        nx = np.where(on_x, nl * cy_, np.where(on_z, nl * sy_, 0))
        nz = np.where(on_x, -nl * sy_, np.where(on_z, nl * cy_, 0))
        ny = np.where(on_y, nl, 0)
        dx, dy, dz = _flat(D[0])[bi], _flat(D[1])[bi], _flat(D[2])[bi]
        cos_inc = np.abs(nx * dx + ny * dy + nz * dz) / np.sqrt(dx * dx + dy * dy + dz * dz)
        foot = _flat(depth)[bi] / fpix / np.maximum(cos_inc, 0.2)
        _flat(surf.mat)[bi] = bm
        _flat(surf.ta)[bi] = (a_ + offa) * inv_texel
        _flat(surf.tb)[bi] = (b_ + offb) * inv_texel
        _flat(surf.lod)[bi] = np.log2(np.maximum(foot * inv_texel, 1e-6))
        lam = np.maximum(0, nx * f32(sc.sun[0]) + ny * f32(sc.sun[1]) + nz * f32(sc.sun[2]))
        # Cheap ambient occlusion: darken the bottom 0.5 m of vertical faces near the ground.
        height_above_ground = -_flat(P[1])[bi]
        ao = 1 - 0.25 * np.clip(1 - height_above_ground / 0.5, 0, 1) * ~on_y
        _flat(surf.shade)[bi] = (sc.ambient + (1 - sc.ambient) * lam) * ao
        surf.tint.reshape(-1, 3)[bi] = np.stack([tr, tg_, tbl], 1)


def _paint_markings(rgb: np.ndarray, shade: np.ndarray, ground: _GroundFootprint) -> None:
    """Lane markings: box-filtered coverage of stripes across (|d|) and dashes along (z), in place."""
    road = ground.abs_d < ROAD_HALF + 0.5
    gi, adr, zr = ground.index[road], ground.abs_d[road], ground.z[road]
    wa, wz = np.maximum(ground.w_across[road], 1e-3), np.maximum(ground.w_along[road], 1e-3)
    base = rgb.reshape(-1, 3)[gi]
    sh = _flat(shade)[gi][:, None]
    for lo_, hi_, dashed, paint in MARKINGS:
        cov = np.clip((np.minimum(adr + wa / 2, hi_) - np.maximum(adr - wa / 2, lo_)) / wa, 0, 1)
        if dashed:
            cov = cov * _dash_coverage(zr, wz)
        base = base + cov[:, None] * (np.asarray(paint, np.float32) * sh - base)
    rgb.reshape(-1, 3)[gi] = base


def _dash_coverage(z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Fraction of [z - w/2, z + w/2] covered by dashes [k P, k P + L): exact box filter via the integral."""

    def F(x):
        return np.floor(x / DASH_PERIOD) * DASH_LEN + np.minimum(np.mod(x, DASH_PERIOD), DASH_LEN)

    return (F(z + w / 2) - F(z - w / 2)) / w
