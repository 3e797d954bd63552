"""Procedural KITTI-like driving sequences with exact depth, optical-flow and pose ground truth.

KITTI cannot be downloaded here, so training and the evaluation code are exercised
on synthetic scenes written in KITTI's own encodings (see ``docs/synthetic_data.md``).

How a frame is made (numpy + OpenCV only, no torch):

* The scene is a flat ground plane (road with lane markings, sidewalks, grass),
  yaw-oriented boxes (buildings, walls, poles, trees, parked and moving cars,
  far backdrop blocks) and a world-fixed sky sphere of radius >= 1000 m. The sky
  has a *finite* depth so its flow is exact; it is beyond the 256 m that a KITTI
  uint16 depth PNG can hold, so depth PNGs store 0 (= no measurement) there, as
  KITTI's LiDAR ground truth does for the sky.
* Every pixel is ray-cast analytically (vectorised numpy). Rays are
  ``D = R_cw @ K^-1 [u, v, 1]`` so the ray parameter of a hit *is* its z-depth.
  Boxes are only tested inside the image rectangle their (near-plane clipped)
  corners project to.
* Geometry (depth, hit points, flow) is cast at the pixel centres of the output
  grid, u = 0..W-1, v = 0..H-1, in float64. Colour is cast on a 2x2 supersampled
  grid (offsets +-0.25 px) in float32 and area-downsampled, textures are
  mip-mapped (trilinear), lane markings are box-filtered analytically.
* Flow t -> t+1: each hit point is moved by the camera motion (and, on a moving
  car, by that car's own rigid motion) and projected into frame t+1. ``occ``
  validity = it lands inside [0, W-1] x [0, H-1] in front of the camera; ``noc``
  additionally requires it to be visible in frame t+1: its depth there is not
  behind all four rendered depths around its landing point (on a plane inverse
  depth is linear in the image, so a visible point is never behind all four).

``python -m training.synth --help`` for the command line.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from geonet_infer.errors import GeoNetInputError
from geonet_infer.io import (atomic_write, write_calib_K, write_depth_kitti, write_flow_kitti, write_image,
                             write_kitti_poses, write_mask)

GENERATOR_VERSION = 1

# KITTI raw 2011_09_26 P_rect_02 (fx, cx, cy) for a 1242 x 375 image; scaled to (H, W).
KITTI_FX, KITTI_FY, KITTI_CX, KITTI_CY, KITTI_W, KITTI_H = 721.5377, 721.5377, 609.5593, 172.854, 1242, 375

CAM_HEIGHT = 1.65  # KITTI camera height above the road, metres
NEAR = 0.05  # near plane used to clip boxes before projecting them
MAX_PNG_DEPTH = 65535 / 256.0  # largest depth a KITTI uint16 PNG can hold
VIS_REL_TOL = 1e-3  # noc test: point may be this much (relative) behind the visible surface

# Surface ids in the id image; box k has id BOX0 + k.
SKY, GROUND, BOX0 = 0, 1, 2

# Road layout in "road coordinates" d = x - x_centre(z) (metres, + = right).
LANE = 3.5
ROAD_HALF = 9.5  # 2 lanes each way (to 7 m) + parking strip
SIDEWALK_OUT = 13.5
EGO_LANE = 1.75
# (|d| from, |d| to, dashed, RGB): double centre line, dashed lane divider, solid edge line.
MARKINGS = ((0.07, 0.17, False, (0.85, 0.72, 0.25)), (3.44, 3.56, True, (0.88, 0.88, 0.85)),
            (6.90, 7.05, False, (0.88, 0.88, 0.85)))
DASH_LEN, DASH_PERIOD = 3.0, 9.0

# ---------------------------------------------------------------------------- materials
(M_ASPHALT, M_SIDEWALK, M_GRASS, M_FACADE_A, M_FACADE_B, M_BRICK, M_CONCRETE, M_PAINT, M_GLASS,
 M_TYRE, M_METAL, M_FOLIAGE, M_BARK, M_SKY, M_HILL) = range(15)
N_MAT = 15
TILE = 128  # texels per tile side
PAD = 2  # wrap padding around each tile in the atlas (bilinear needs 1)
LMAX = 6  # mip levels 0..6 (128 -> 2 texels)
# metres per texel; the sky is addressed directly in texels (1.0)
TEXEL_M = np.array([0.03, 0.025, 0.02, 0.025, 0.025, 0.0125, 0.03, 0.02, 0.02, 0.02, 0.01, 0.015,
                    0.01, 1.0, 0.4], dtype=np.float32)
SKY_REPEATS = 8  # sky tile repeats around the horizon
PSF_SIGMA = 0.5  # Gaussian optical blur, output pixels (applied before the 2x2 area downsample)
LOD_BIAS = 0.0  # added to every mip level: > 0 blurs textures slightly


def kitti_like_K(height: int, width: int) -> np.ndarray:
    """KITTI's P_rect_02 intrinsics scaled to (height, width): (3, 3) float64, fx ~ 0.58 W."""
    sx, sy = width / KITTI_W, height / KITTI_H
    return np.array([[KITTI_FX * sx, 0, KITTI_CX * sx], [0, KITTI_FY * sy, KITTI_CY * sy], [0, 0, 1]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about +y (down): maps forward (0, 0, 1) to (sin a, 0, cos a), i.e. a > 0 turns right."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def make_T(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


# ---------------------------------------------------------------------------- textures
def fbm(rng: np.random.Generator, size: int, beta: float, channels: int = 1) -> np.ndarray:
    """Tileable multi-scale noise: white noise shaped by a 1/f**beta amplitude spectrum.

    Returns (size, size) or (size, size, channels) float32, zero mean, unit std.
    The FFT makes it periodic, so tiles wrap without seams.
    """
    white = rng.standard_normal((channels, size, size))
    f = np.fft.fftfreq(size)
    r = np.sqrt(f[:, None] ** 2 + f[None, :] ** 2)
    r[0, 0] = 1.0
    spec = np.fft.fft2(white) * r ** (-beta)
    spec[:, 0, 0] = 0.0
    out = np.real(np.fft.ifft2(spec))
    out /= out.std(axis=(1, 2), keepdims=True) + 1e-12
    out = np.moveaxis(out, 0, -1).astype(np.float32)
    return out[..., 0] if channels == 1 else out


def _rgba(rgb: np.ndarray, tintable) -> np.ndarray:
    a = np.broadcast_to(np.asarray(tintable, dtype=np.float32), rgb.shape[:2])
    return np.dstack([np.clip(rgb, 0, 1.5), a]).astype(np.float32)


def _grey(v: np.ndarray, rgb=(1.0, 1.0, 1.0)) -> np.ndarray:
    return v[..., None] * np.asarray(rgb, dtype=np.float32)


def make_tiles(rng: np.random.Generator) -> np.ndarray:
    """All material tiles for one sequence: (N_MAT, TILE, TILE, 4) float32.

    RGB is the albedo, A is how much the per-object tint applies (1 = paint,
    0 = glass/mortar). Row index = texture v (up the wall / along the road).
    """
    S = TILE
    yy, xx = np.mgrid[0:S, 0:S].astype(np.float32)
    tiles = np.zeros((N_MAT, S, S, 4), np.float32)

    # Asphalt: grain + blotches + a few dark repairs.
    v = 0.33 + 0.035 * fbm(rng, S, 1.2) + 0.03 * fbm(rng, S, 0.2) + 0.02 * (fbm(rng, S, 1.6) > 1.2)
    tiles[M_ASPHALT] = _rgba(_grey(v, (1.0, 0.99, 0.97)), 0.3)
    # Sidewalk: 0.8 m slabs with dark joints, per-slab shade.
    slab = rng.uniform(-0.05, 0.05, (4, 4))[(yy // 32).astype(int), (xx // 32).astype(int)]
    joint = ((xx % 32) < 1.5) | ((yy % 32) < 1.5)
    v = 0.62 + slab + 0.04 * fbm(rng, S, 1.0) - 0.25 * joint
    tiles[M_SIDEWALK] = _rgba(_grey(v, (1.0, 0.98, 0.95)), 0.3)
    # Grass.
    n = fbm(rng, S, 0.8, 3)
    tiles[M_GRASS] = _rgba(np.array([0.26, 0.40, 0.14]) * (1 + 0.30 * n[..., :1]) + 0.04 * n, 0.6)
    # Facades: one 3.2 m x 3.2 m bay per tile; A has one wide window, B two narrow ones.
    for mat, rects in ((M_FACADE_A, ((22, 106, 30, 104),)), (M_FACADE_B, ((14, 54, 22, 110), (74, 114, 22, 110)))):
        wall = 0.78 + 0.05 * fbm(rng, S, 1.1)
        glass = 0.16 + 0.10 * (yy / S) + 0.05 * fbm(rng, S, 1.5)
        rgb = _grey(wall)
        tintable = np.ones((S, S), np.float32)
        for x0, x1, y0, y1 in rects:
            win = (xx >= x0) & (xx < x1) & (yy >= y0) & (yy < y1)
            inner = (xx >= x0 + 3) & (xx < x1 - 3) & (yy >= y0 + 3) & (yy < y1 - 3)
            sill = (yy >= y0 - 4) & (yy < y0) & (xx >= x0 - 3) & (xx < x1 + 3)
            rgb = np.where(inner[..., None], np.dstack([glass * 0.8, glass * 0.95, glass * 1.15]), rgb)
            rgb = np.where((win & ~inner)[..., None], 0.92, rgb)
            rgb = np.where(sill[..., None], 0.55, rgb)
            tintable[win | sill] = 0.0
        tiles[mat] = _rgba(rgb, tintable)
    # Brick: 0.4 x 0.1 m bricks (32 x 8 texels), running bond, light mortar.
    row = (yy // 8).astype(int)
    col = ((xx + 16 * (row % 2)) // 32).astype(int) % 4
    brick_shade = rng.uniform(-0.12, 0.12, (16, 4))[row, col]
    mortar = ((yy % 8) < 1.2) | (((xx + 16 * (row % 2)) % 32) < 1.5)
    v = 0.62 + brick_shade + 0.05 * fbm(rng, S, 0.7)
    rgb = np.where(mortar[..., None], 0.75, _grey(v))
    tiles[M_BRICK] = _rgba(rgb, (~mortar).astype(np.float32))
    # Concrete: panels every 1.92 m with stains.
    v = 0.66 + 0.06 * fbm(rng, S, 1.3) - 0.06 * np.clip(fbm(rng, S, 1.8), 0, None) - 0.2 * ((xx % 64) < 1.5)
    tiles[M_CONCRETE] = _rgba(_grey(v), 1.0)
    # Car paint with door seams.
    v = 0.80 + 0.025 * fbm(rng, S, 1.0) - 0.45 * (((xx % 48) < 1.2) | ((yy % 64) < 1.0))
    tiles[M_PAINT] = _rgba(_grey(v), 1.0)
    g = 0.12 + 0.08 * (yy / S) + 0.06 * fbm(rng, S, 1.4) + 0.08 * np.clip(fbm(rng, S, 2.0), 0, None)
    tiles[M_GLASS] = _rgba(np.dstack([g * 0.85, g * 0.95, g * 1.1]), 0.0)
    tiles[M_TYRE] = _rgba(_grey(0.09 + 0.02 * fbm(rng, S, 0.6)), 0.0)
    # Metal: vertical streaks (noise stretched along v).
    streak = cv2.resize(fbm(rng, S, 0.7)[:8], (S, S), interpolation=cv2.INTER_LINEAR)
    tiles[M_METAL] = _rgba(_grey(0.55 + 0.08 * streak + 0.03 * fbm(rng, S, 0.5)), 1.0)
    leaves = fbm(rng, S, 0.9)
    v = 0.5 + 0.45 * np.tanh(1.5 * leaves)
    tiles[M_FOLIAGE] = _rgba(_grey(v * 0.55 + 0.05, (0.55, 0.85, 0.35)), 1.0)
    bark = cv2.resize(fbm(rng, S, 0.8)[:16], (S, S), interpolation=cv2.INTER_LINEAR)
    tiles[M_BARK] = _rgba(_grey(0.35 + 0.08 * bark, (0.85, 0.65, 0.45)), 0.5)
    # Sky: blue with soft clouds.
    cloud = np.clip(fbm(rng, S, 1.3) * 0.6 + rng.uniform(-0.6, 0.2), 0, 1) ** 0.8
    blue = np.array([0.42, 0.60, 0.88], np.float32)
    tiles[M_SKY] = _rgba(blue * (1 - cloud[..., None]) + 0.93 * cloud[..., None], 0.0)
    # Far hills / backdrop: low-contrast, already hazy.
    tiles[M_HILL] = _rgba(_grey(0.62 + 0.06 * fbm(rng, S, 1.2), (0.85, 0.95, 1.0)), 1.0)
    return tiles


def _pyr_down_wrap(tile: np.ndarray) -> np.ndarray:
    """Halve a tileable image; wrap-padding keeps the result tileable and aligned (x_{l+1} = x_l / 2)."""
    p = np.pad(tile, ((4, 4), (4, 4), (0, 0)), mode="wrap")
    return cv2.pyrDown(p)[2:-2, 2:-2]


def build_mip_atlas(tiles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Stack mip levels of all tiles into one atlas.

    Returns:
        atlas: (Ha, Wa, 4) float32. Level l occupies rows y0[l] .. y0[l] + S_l + 2*PAD;
            tile m of level l sits at x = m * (S_l + 2*PAD) + PAD, S_l = TILE >> l,
            surrounded by a wrap copy of itself.
        y0: (LMAX + 1,) int row offset of each level.
    """
    levels = [list(tiles)]
    for _ in range(LMAX):
        levels.append([_pyr_down_wrap(t) for t in levels[-1]])
    y0 = np.zeros(LMAX + 1, np.int64)
    for l in range(1, LMAX + 1):
        y0[l] = y0[l - 1] + (TILE >> (l - 1)) + 2 * PAD
    atlas = np.zeros((int(y0[-1]) + (TILE >> LMAX) + 2 * PAD, len(tiles) * (TILE + 2 * PAD), 4), np.float32)
    for l, lev in enumerate(levels):
        s = TILE >> l
        for m, t in enumerate(lev):
            x = m * (s + 2 * PAD)
            atlas[y0[l]:y0[l] + s + 2 * PAD, x:x + s + 2 * PAD] = np.pad(t, ((PAD, PAD), (PAD, PAD), (0, 0)), mode="wrap")
    return atlas, y0


def sample_atlas(atlas: np.ndarray, y0: np.ndarray, mat: np.ndarray, ta: np.ndarray, tb: np.ndarray,
                 lod: np.ndarray) -> np.ndarray:
    """Trilinear (mip-mapped) texture lookup.

    Args:
        mat: (h, w) int material index; ta, tb: (h, w) float32 texel coordinates at
            level 0 (any range, wrapped); lod: (h, w) float32 mip level (clipped to [0, LMAX]).
    Returns:
        (h, w, 4) float32 RGBA.
    """
    lod = np.clip(lod + LOD_BIAS, 0, LMAX)
    l0 = np.minimum(lod.astype(np.int32), LMAX - 1)
    frac = (lod - l0)[..., None]
    # mod(t * S_l / TILE, S_l) == S_l * frac(t / TILE): wrap once, reuse for both levels.
    fa = ta * np.float32(1 / TILE)
    fa -= np.floor(fa)
    fb = tb * np.float32(1 / TILE)
    fb -= np.floor(fb)
    fa += mat
    pad_x = mat * np.float32(2 * PAD) + np.float32(PAD)
    s0 = (TILE >> np.arange(LMAX + 1)).astype(np.float32)[l0]
    y0f = y0.astype(np.float32) + np.float32(PAD)
    out = None
    for s, yoff, w in ((s0, y0f[l0], 1 - frac), (s0 * np.float32(0.5), y0f[l0 + 1], frac)):
        x = s * fa + pad_x  # = PAD + mat * (S_l + 2 PAD) + S_l * frac(ta / TILE)
        y = s * fb + yoff
        c = cv2.remap(atlas, x, y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out = c * w if out is None else out + c * w
    return out


# ---------------------------------------------------------------------------- scene
@dataclass
class Road:
    """Gently curving road: centre line x_c(z) = sum of two sinusoids (metres)."""

    amp: np.ndarray  # (2,)
    freq: np.ndarray  # (2,) rad / m
    phase: np.ndarray  # (2,)

    def centre(self, z):
        z = np.asarray(z, dtype=np.float64)
        return sum(a * (np.sin(f * z + p) - np.sin(p)) for a, f, p in zip(self.amp, self.freq, self.phase))

    def centre_f32(self, z: np.ndarray) -> np.ndarray:
        out = np.zeros_like(z)
        for a, f, p in zip(self.amp, self.freq, self.phase):
            out += np.float32(a) * (np.sin(np.float32(f) * z + np.float32(p)) - np.float32(np.sin(p)))
        return out

    def heading(self, z):
        """Yaw of the road direction at z (radians, + = towards +x)."""
        z = np.asarray(z, dtype=np.float64)
        return np.arctan(sum(a * f * np.cos(f * z + p) for a, f, p in zip(self.amp, self.freq, self.phase)))


@dataclass
class Scene:
    """Everything needed to render one sequence (road world frame: x right, y down, z forward, ground y = 0)."""

    K: np.ndarray  # (3, 3)
    height: int
    width: int
    road: Road
    T_wc: np.ndarray  # (M, 4, 4) camera-to-road-world per frame
    # boxes (B,): static ones fixed, moving ones (group >= 0) re-posed per frame from their group
    box_centre: np.ndarray  # (B, 3) static centre, or centre in the group frame for moving boxes
    box_yaw: np.ndarray  # (B,)
    box_half: np.ndarray  # (B, 3) half extents in the box frame
    box_mat: np.ndarray  # (B,) int
    box_tint: np.ndarray  # (B, 3)
    box_texoff: np.ndarray  # (B, 2) metres, texture phase
    box_group: np.ndarray  # (B,) int, -1 = static
    group_T: np.ndarray  # (G, M, 4, 4) group-to-world per frame
    sky_centre: np.ndarray  # (3,)
    sky_radius: float
    sun: np.ndarray  # (3,) unit vector towards the sun
    ambient: float
    gain: float
    atlas: np.ndarray
    atlas_y0: np.ndarray

    def boxes_at(self, t: int) -> tuple[np.ndarray, np.ndarray]:
        """World centres (B, 3) and yaws (B,) of all boxes at frame t."""
        centre = self.box_centre.copy()
        yaw = self.box_yaw.copy()
        mov = np.flatnonzero(self.box_group >= 0)
        if len(mov):
            G = self.group_T[self.box_group[mov], t]  # (n, 4, 4)
            centre[mov] = np.einsum("nij,nj->ni", G[:, :3, :3], self.box_centre[mov]) + G[:, :3, 3]
            yaw[mov] = self.box_yaw[mov] + np.arctan2(G[:, 0, 2], G[:, 2, 2])
        return centre, yaw


class _BoxList:
    """Accumulates boxes while building a scene."""

    def __init__(self):
        self.rows = []

    def add(self, centre, yaw, half, mat, tint, texoff=(0.0, 0.0), group=-1):
        self.rows.append((np.asarray(centre, float), float(yaw), np.asarray(half, float), int(mat),
                          np.asarray(tint, float), np.asarray(texoff, float), int(group)))

    def arrays(self):
        if not self.rows:
            z3 = np.zeros((0, 3))
            return z3, np.zeros(0), z3, np.zeros(0, int), z3, np.zeros((0, 2)), np.zeros(0, int)
        cols = list(zip(*self.rows))
        return (np.stack(cols[0]), np.array(cols[1]), np.stack(cols[2]), np.array(cols[3]),
                np.stack(cols[4]), np.stack(cols[5]), np.array(cols[6]))


def _smooth_noise(rng: np.random.Generator, n: int, amp: float, periods=(40, 160)) -> np.ndarray:
    """(n,) sum of three random sinusoids with amplitude ~amp: smooth jitter over frames."""
    t = np.arange(n)
    out = np.zeros(n)
    for _ in range(3):
        out += amp / 3 * np.sin(2 * np.pi * t / rng.uniform(*periods) + rng.uniform(0, 2 * np.pi))
    return out


def make_trajectory(rng: np.random.Generator, frames: int, road: Road) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ego camera at 10 Hz: speed 0.4-1.5 m/frame, following its lane on the curving road.

    Returns:
        T_wc: (M, 4, 4) camera-to-road-world; z: (M,) road position; v: (M,) speed (m/frame).
    """
    v = np.empty(frames)
    speed, target = rng.uniform(0.5, 1.4), rng.uniform(0.4, 1.5)
    for t in range(frames):
        if rng.random() < 1 / 30:
            target = rng.uniform(0.4, 1.5)
        speed += np.clip(target - speed, -0.04, 0.04)  # ~0.4 m/s^2 at 10 Hz
        v[t] = speed
    z = np.concatenate([[0.0], np.cumsum(v[:-1])])
    d = EGO_LANE + _smooth_noise(rng, frames, 0.25, (60, 200))
    x = road.centre(z) + d
    # Heading from the path tangent (dx/dz of the road plus lane drift) plus small steering jitter.
    dxdz = np.gradient(x, z) if frames > 1 else np.tan(road.heading(z))
    yaw = np.arctan(dxdz) + np.radians(_smooth_noise(rng, frames, 0.3, (20, 80)))
    pitch = np.radians(_smooth_noise(rng, frames, 0.5, (15, 60)))
    roll = np.radians(_smooth_noise(rng, frames, 0.3, (15, 60)))
    y = -CAM_HEIGHT + _smooth_noise(rng, frames, 0.02, (10, 40))
    T = np.stack([make_T(rot_y(yaw[i]) @ rot_x(pitch[i]) @ rot_z(roll[i]), (x[i], y[i], z[i])) for i in range(frames)])
    return T, z, v


def _pastel(rng, lo=0.55, hi=1.0):
    return rng.uniform(lo, hi, 3)


CAR_COLOURS = np.array([[0.9, 0.9, 0.9], [0.15, 0.15, 0.17], [0.6, 0.62, 0.65], [0.7, 0.1, 0.1],
                        [0.15, 0.25, 0.6], [0.85, 0.8, 0.6], [0.2, 0.45, 0.25], [0.9, 0.6, 0.1]])


def add_car(boxes: _BoxList, rng, centre_xz, yaw, group=-1):
    """A car as 3 boxes (wheels/underbody, body, cabin), bottom on the ground.

    With group >= 0 the centres are in the group's own frame (origin on the ground
    under the car centre), else in world coordinates.
    """
    L, Wd = rng.uniform(3.9, 4.8), rng.uniform(1.65, 1.85)
    tint = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.85, 1.1)
    if group >= 0:
        origin, R, yaw0 = np.zeros(3), np.eye(3), 0.0
    else:
        origin, R, yaw0 = np.array([centre_xz[0], 0.0, centre_xz[1]]), rot_y(yaw), yaw
    off = rng.uniform(0, 5, 2)
    hb = rng.uniform(0.95, 1.15)  # body top
    parts = ((0.0, 0.45 / 2, (0.45 * Wd, 0.45 / 2, 0.42 * L), M_TYRE, (1, 1, 1)),
             (0.0, 0.35 + (hb - 0.35) / 2, (Wd / 2, (hb - 0.35) / 2, L / 2), M_PAINT, tint),
             (-0.08 * L, hb + 0.23, (0.43 * Wd, 0.23, 0.27 * L), M_GLASS, tint))
    for dz, yc, half, mat, tn in parts:
        c = origin + R @ np.array([0.0, -yc, dz])
        boxes.add(c, yaw0, half, mat, tn, off, group)


def make_scene(rng: np.random.Generator, frames: int, height: int, width: int) -> Scene:
    """Random road, ego trajectory, static dressing, traffic, lighting and textures for one sequence."""
    K = kitti_like_K(height, width)
    # Road: max heading ~20 deg, curvature radius >~ 70 m.
    amp = np.array([rng.uniform(0, 14), rng.uniform(0, 3)])
    wl = np.array([rng.uniform(250, 600), rng.uniform(90, 200)])
    freq = 2 * np.pi / wl
    amp = np.minimum(amp, 0.18 / freq)
    road = Road(amp, freq, rng.uniform(0, 2 * np.pi, 2))
    T_wc, ego_z, _ = make_trajectory(rng, frames, road)
    z_end = ego_z[-1]
    z_lo, z_hi = -30.0, z_end + 170.0

    def place(z, d):
        return np.array([road.centre(z) + d, road.heading(z)])

    boxes = _BoxList()
    for side in (-1, 1):
        z = z_lo + rng.uniform(0, 10)
        while z < z_hi:  # segments of buildings / wall / open land
            seg_end = z + rng.uniform(40, 160)
            kind = rng.choice(["buildings", "wall", "open"], p=[0.6, 0.15, 0.25])
            while z < min(seg_end, z_hi):
                if kind == "buildings":
                    L, depth = rng.uniform(8, 30), rng.uniform(8, 20)
                    h = 3.2 * rng.integers(2, 8) + rng.uniform(0, 1.0)
                    setback = SIDEWALK_OUT + rng.uniform(0, 4) * (rng.random() < 0.5)
                    zc = z + L / 2
                    x, yaw = place(zc, side * (setback + depth / 2))
                    mat = rng.choice([M_FACADE_A, M_FACADE_B, M_BRICK, M_CONCRETE], p=[0.35, 0.25, 0.25, 0.15])
                    tint = _pastel(rng, 0.5, 1.0) if mat != M_BRICK else rng.uniform([0.8, 0.35, 0.25], [1.0, 0.6, 0.45])
                    boxes.add((x, -h / 2, zc), yaw, (depth / 2, h / 2, L / 2), mat, tint)
                    z += L + (rng.uniform(0, 6) if rng.random() < 0.5 else 0.0)
                elif kind == "wall":
                    L, h = rng.uniform(15, 60), rng.uniform(1.0, 2.6)
                    zc = z + L / 2
                    x, yaw = place(zc, side * (SIDEWALK_OUT + 0.2))
                    mat = rng.choice([M_BRICK, M_CONCRETE])
                    boxes.add((x, -h / 2, zc), yaw, (0.15, h / 2, L / 2), mat, _pastel(rng, 0.7), rng.uniform(0, 5, 2))
                    z += L
                else:  # open: trees behind the sidewalk
                    L = rng.uniform(6, 14)
                    _add_tree(boxes, rng, place, z + L / 2, side * rng.uniform(15, 30))
                    z += L
        # Street furniture: poles (some with lamp arms or signs), sidewalk trees.
        z = z_lo + rng.uniform(0, 20)
        while z < z_hi:
            x, yaw = place(z, side * 10.2)
            h = rng.uniform(4.5, 7.5)
            boxes.add((x, -h / 2, z), yaw, (0.07, h / 2, 0.07), M_METAL, _pastel(rng, 0.6), rng.uniform(0, 5, 2))
            r = rng.random()
            if r < 0.4:  # lamp arm over the road
                xa, yawa = place(z, side * (10.2 - 0.9))
                boxes.add((xa, -h + 0.08, z), yawa, (0.9, 0.06, 0.08), M_METAL, _pastel(rng, 0.6))
            elif r < 0.7:  # sign board
                boxes.add((x, -2.6, z), yaw, (0.4, 0.35, 0.03), M_PAINT,
                          rng.choice([(1.0, 0.25, 0.2), (0.2, 0.4, 0.9), (0.95, 0.85, 0.2), (0.9, 0.9, 0.9)]))
            if rng.random() < 0.35:
                _add_tree(boxes, rng, place, z + rng.uniform(4, 8), side * 11.6)
            z += rng.uniform(15, 35)
        # Parked cars on the parking strip, in runs.
        z = z_lo + rng.uniform(0, 15)
        while z < z_hi:
            run_end = z + rng.uniform(10, 60)
            if rng.random() < 0.55:
                while z < run_end:
                    x, yaw = place(z, side * rng.uniform(8.2, 8.4))
                    add_car(boxes, rng, (x, z), yaw + rng.uniform(-0.03, 0.03))
                    z += rng.uniform(5.0, 9.0)
            z = run_end + rng.uniform(5, 40)
        # Far backdrop (hills, distant blocks) 60-250 m out, world-fixed.
        z = -100.0
        while z < z_end + 500:
            L, h = rng.uniform(30, 150), rng.uniform(8, 50)
            dist = rng.uniform(60, 250)
            x, yaw = place(z + L / 2, side * (dist + 10))
            mat = rng.choice([M_HILL, M_CONCRETE, M_FACADE_A])
            tint = np.array([0.8, 0.85, 0.95]) * rng.uniform(0.8, 1.1)
            boxes.add((x, -h / 2 + 0.5, z + L / 2), yaw + rng.uniform(-0.3, 0.3), (10, h / 2, L / 2), mat, tint,
                      rng.uniform(0, 20, 2))
            z += L * rng.uniform(0.5, 1.2)

    # Traffic: each moving car is a rigid group of boxes with a pose per frame.
    groups = []
    t_idx = np.arange(frames)

    def group_poses(zs, d):
        x = road.centre(zs) + d
        yaw = road.heading(zs)
        return np.stack([make_T(rot_y(yaw[i]), (x[i], 0.0, zs[i])) for i in range(frames)])

    if rng.random() < 0.7:  # lead car in the ego lane, never closer than ~9 m
        gap = rng.uniform(14, 35) + _smooth_noise(rng, frames, rng.uniform(0, 10), (40, 150))
        groups.append(group_poses(ego_z + np.maximum(gap, 9.0), EGO_LANE))
    for d, direction in ((LANE + EGO_LANE, 1), (-EGO_LANE, -1), (-(LANE + EGO_LANE), -1)):
        if rng.random() < 0.25:
            continue
        speed = direction * rng.uniform(0.4, 1.8)
        # Spread cars over the stretch of road they will cross during the sequence.
        span_lo, span_hi = (-60, z_end + 120) if direction > 0 else (0, z_end + 120 + abs(speed) * frames)
        z0 = span_lo + rng.uniform(0, 15)
        while z0 < span_hi:
            groups.append(group_poses(z0 + speed * t_idx, d))
            z0 += rng.uniform(12, 60)
    for g in range(len(groups)):
        add_car(boxes, rng, None, 0.0, group=g)
    group_T = np.stack(groups) if groups else np.zeros((0, frames, 4, 4))

    (centre, yaw, half, mat, tint, texoff, group) = boxes.arrays()
    path = np.linalg.norm(T_wc[-1, :3, 3] - T_wc[0, :3, 3])
    sky_c = 0.5 * (T_wc[0, :3, 3] + T_wc[-1, :3, 3])
    sky_c[1] = -CAM_HEIGHT
    el, az = np.radians(rng.uniform(25, 60)), rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])
    atlas, y0 = build_mip_atlas(make_tiles(rng))
    return Scene(K, height, width, road, T_wc, centre, yaw, half, mat, tint, texoff, group, group_T,
                 sky_c, 1000.0 + path, sun, rng.uniform(0.35, 0.5), rng.uniform(0.9, 1.1), atlas, y0)


def _add_tree(boxes: _BoxList, rng, place, z, d):
    x, yaw = place(z, d)
    h = rng.uniform(1.8, 3.0)
    boxes.add((x, -h / 2, z), yaw, (0.15, h / 2, 0.15), M_BARK, (1, 1, 1), rng.uniform(0, 5, 2))
    r = rng.uniform(1.0, 2.2)
    boxes.add((x, -h - r * 0.8, z), yaw + rng.uniform(-0.5, 0.5), (r, r * 0.8, r), M_FOLIAGE,
              rng.uniform([0.7, 0.8, 0.6], [1.0, 1.1, 0.9]), rng.uniform(0, 5, 2))


# ---------------------------------------------------------------------------- rendering
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
            c = dt(o @ o - sc.sky_radius ** 2)
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
    def colour(self, t_idx: int) -> np.ndarray:
        """Anti-aliased RGB of frame t_idx: (H, W, 3) uint8."""
        sc = self.scene
        s = self.ss
        centre, yaw = sc.boxes_at(t_idx)
        depth, ids, D = self.cast(t_idx, s, (centre, yaw))
        C = sc.T_wc[t_idx, :3, 3].astype(np.float32)
        f32 = np.float32
        P = [C[i] + depth * D[i] for i in range(3)]
        h, w = depth.shape
        mat = np.zeros((h, w), np.float32)
        ta = np.zeros((h, w), np.float32)
        tb = np.zeros((h, w), np.float32)
        lod = np.zeros((h, w), np.float32)
        shade = np.ones((h, w), np.float32)
        tint = np.ones((h, w, 3), np.float32)
        flat = lambda a: a.reshape(-1)  # noqa: E731
        ids_f = flat(ids)
        fpix = f32(min(sc.K[0, 0], sc.K[1, 1]) * s)  # pixels per unit tan-angle on this grid
        diffuse_ground = max(0.0, -sc.sun[1])

        # Ground: material by lateral road coordinate, markings added after the lookup.
        g = np.flatnonzero(ids_f == GROUND)
        gx, gz, gt = flat(P[0])[g], flat(P[2])[g], flat(depth)[g]
        d = gx - sc.road.centre_f32(gz)
        ad = np.abs(d)
        gm = np.where(ad < ROAD_HALF, M_ASPHALT, np.where(ad < SIDEWALK_OUT, M_SIDEWALK, M_GRASS)).astype(np.float32)
        cam_h = f32(-C[1])
        w_across = gt / fpix
        w_along = gt * gt / (fpix * cam_h)
        foot = np.maximum(w_across, w_along)
        inv_texel = (1 / TEXEL_M)[gm.astype(np.int32)]
        flat(mat)[g] = gm
        flat(ta)[g] = d * inv_texel
        flat(tb)[g] = gz * inv_texel
        flat(lod)[g] = np.log2(np.maximum(foot * inv_texel, 1e-6))
        flat(shade)[g] = sc.ambient + (1 - sc.ambient) * diffuse_ground

        # Sky: direction from the sphere centre -> (azimuth, elevation) texel coordinates.
        k = np.flatnonzero(ids_f == SKY)
        sx = flat(P[0])[k] - f32(sc.sky_centre[0])
        sy = flat(P[1])[k] - f32(sc.sky_centre[1])
        sz = flat(P[2])[k] - f32(sc.sky_centre[2])
        az = np.arctan2(sx, sz)
        el = np.arcsin(np.clip(-sy / f32(sc.sky_radius), -1, 1))
        texels_per_rad = f32(SKY_REPEATS * TILE / (2 * np.pi))
        flat(mat)[k] = M_SKY
        flat(ta)[k] = az * texels_per_rad
        flat(tb)[k] = el * texels_per_rad
        flat(lod)[k] = np.log2(texels_per_rad / fpix)
        flat(shade)[k] = 1.0 + 0.25 * (1 - np.clip(el / 0.35, 0, 1))  # brighter towards the horizon

        # Boxes: hit point in the box frame -> face, normal, face texture coordinates.
        bi = np.flatnonzero(ids_f >= BOX0)
        if len(bi):
            # One row gather of a per-box float32 table (np.take) is much cheaper than one per field.
            table = np.concatenate([centre, np.cos(yaw)[:, None], np.sin(yaw)[:, None], sc.box_half,
                                    sc.box_texoff, (1 / TEXEL_M)[sc.box_mat][:, None], sc.box_mat[:, None],
                                    sc.box_tint], axis=1).astype(np.float32)
            tb_ = np.take(table, ids_f[bi] - BOX0, axis=0)
            cx_, cy0, cz_, cy_, sy_, ex, ey, ez, offa, offb, inv_texel, bm, tr, tg_, tbl = tb_.T
            px, py, pz = flat(P[0])[bi] - cx_, flat(P[1])[bi] - cy0, flat(P[2])[bi] - cz_
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
            dx, dy, dz = flat(D[0])[bi], flat(D[1])[bi], flat(D[2])[bi]
            cos_inc = np.abs(nx * dx + ny * dy + nz * dz) / np.sqrt(dx * dx + dy * dy + dz * dz)
            foot = flat(depth)[bi] / fpix / np.maximum(cos_inc, 0.2)
            flat(mat)[bi] = bm
            flat(ta)[bi] = (a_ + offa) * inv_texel
            flat(tb)[bi] = (b_ + offb) * inv_texel
            flat(lod)[bi] = np.log2(np.maximum(foot * inv_texel, 1e-6))
            lam = np.maximum(0, nx * f32(sc.sun[0]) + ny * f32(sc.sun[1]) + nz * f32(sc.sun[2]))
            # Cheap ambient occlusion: darken the bottom 0.5 m of vertical faces near the ground.
            height_above_ground = -flat(P[1])[bi]
            ao = 1 - 0.25 * np.clip(1 - height_above_ground / 0.5, 0, 1) * ~on_y
            flat(shade)[bi] = (sc.ambient + (1 - sc.ambient) * lam) * ao
            tint.reshape(-1, 3)[bi] = np.stack([tr, tg_, tbl], 1)

        rgba = sample_atlas(sc.atlas, sc.atlas_y0, mat, ta, tb, lod)
        alpha = rgba[..., 3:4]
        rgb = rgba[..., :3] * (1 + alpha * (tint - 1)) * shade[..., None]

        # Lane markings: box-filtered coverage of stripes across (|d|) and dashes along (z).
        if len(g):
            road = ad < ROAD_HALF + 0.5
            gi, adr, zr = g[road], ad[road], gz[road]
            wa, wz = np.maximum(w_across[road], 1e-3), np.maximum(w_along[road], 1e-3)
            base = rgb.reshape(-1, 3)[gi]
            sh = flat(shade)[gi][:, None]
            for lo_, hi_, dashed, paint in MARKINGS:
                cov = np.clip((np.minimum(adr + wa / 2, hi_) - np.maximum(adr - wa / 2, lo_)) / wa, 0, 1)
                if dashed:
                    cov = cov * _dash_coverage(zr, wz)
                base = base + cov[:, None] * (np.asarray(paint, np.float32) * sh - base)
            rgb.reshape(-1, 3)[gi] = base

        if PSF_SIGMA > 0:  # camera optics: real lenses do not give 1-pixel-sharp edges
            rgb = cv2.GaussianBlur(rgb, (0, 0), PSF_SIGMA * s)
        rgb = cv2.resize(rgb, (sc.width, sc.height), interpolation=cv2.INTER_AREA) * f32(sc.gain)
        return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def _dash_coverage(z: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Fraction of [z - w/2, z + w/2] covered by dashes [k P, k P + L): exact box filter via the integral."""
    def F(x):
        return np.floor(x / DASH_PERIOD) * DASH_LEN + np.minimum(np.mod(x, DASH_PERIOD), DASH_LEN)
    return (F(z + w / 2) - F(z - w / 2)) / w


# ---------------------------------------------------------------------------- ground truth
@dataclass
class FrameGeom:
    depth: np.ndarray  # (H, W) float64 z-depth
    ids: np.ndarray  # (H, W) int32
    points: np.ndarray  # (H, W, 3) float64 road-world hit points
    moving: np.ndarray  # (H, W) bool


def frame_geometry(r: Renderer, t: int) -> FrameGeom:
    depth, ids, D = r.cast(t, 1)
    C = r.scene.T_wc[t, :3, 3]
    points = np.stack([C[i] + depth * D[i] for i in range(3)], -1)
    grp = np.full(ids.shape, -1)
    box = ids >= BOX0
    grp[box] = r.scene.box_group[ids[box] - BOX0]
    return FrameGeom(depth, ids, points, grp >= 0)


def flow_gt(scene: Scene, t: int, g0: FrameGeom, g1: FrameGeom):
    """Exact flow t -> t+1 at pixel centres.

    Returns:
        flow (H, W, 2) float32 px, noc (H, W) bool, occ (H, W) bool.
    """
    H, W = g0.depth.shape
    P = g0.points.copy()
    grp = np.full((H, W), -1)
    box = g0.ids >= BOX0
    grp[box] = scene.box_group[g0.ids[box] - BOX0]
    for gi in np.unique(grp[grp >= 0]):
        A = scene.group_T[gi, t + 1] @ np.linalg.inv(scene.group_T[gi, t])  # group motion in the world
        m = grp == gi
        P[m] = P[m] @ A[:3, :3].T + A[:3, 3]
    T1 = scene.T_wc[t + 1]
    X = (P - T1[:3, 3]) @ T1[:3, :3]  # into camera t+1
    K = scene.K
    z = X[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = K[0, 0] * X[..., 0] / z + K[0, 2]
        y = K[1, 1] * X[..., 1] / z + K[1, 2]
    u, v = np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))
    flow = np.stack([x - u, y - v], -1)
    occ = (z > NEAR) & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    # Visible in t+1 unless behind all 4 rendered depths around the landing point.
    xc, yc = np.where(occ, x, 0), np.where(occ, y, 0)
    x0 = np.clip(np.floor(xc).astype(int), 0, W - 1)
    y0 = np.clip(np.floor(yc).astype(int), 0, H - 1)
    x1, y1 = np.minimum(x0 + 1, W - 1), np.minimum(y0 + 1, H - 1)
    d1 = g1.depth
    dmax = np.maximum(np.maximum(d1[y0, x0], d1[y0, x1]), np.maximum(d1[y1, x0], d1[y1, x1]))
    noc = occ & (z <= dmax * (1 + VIS_REL_TOL))
    flow = np.where(occ[..., None], flow, 0.0).astype(np.float32)
    return flow, noc, occ


# ---------------------------------------------------------------------------- sequences
def sequence_rng(seed: int, index: int) -> np.random.Generator:
    """Independent RNG per (seed, sequence index): output does not depend on --workers."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(index)]))


def iter_frames(seed: int, index: int, frames: int, height: int = 128, width: int = 416) -> Iterator[dict]:
    """Render one sequence frame by frame.

    Yields per frame t: image (H, W, 3) uint8, depth (H, W) float32 metres (sky ~1000 m),
    ids (H, W) int32, motion_mask (H, W) bool, and for t < M-1 flow (H, W, 2) float32,
    flow_noc / flow_occ (H, W) bool (t -> t+1); plus K and pose (4, 4) camera-to-world in
    the frame-0 camera coordinates (first pose = identity).
    """
    if frames < 2:
        raise GeoNetInputError(None, f"--frames must be >= 2 (got {frames})", "flow needs frame pairs")
    scene = make_scene(sequence_rng(seed, index), frames, height, width)
    r = Renderer(scene)
    poses = np.linalg.inv(scene.T_wc[0]) @ scene.T_wc  # relative to frame 0
    poses[0] = np.eye(4)  # exactly, not up to rounding
    prev = frame_geometry(r, 0)
    for t in range(frames):
        nxt = frame_geometry(r, t + 1) if t + 1 < frames else None
        out = {"image": r.colour(t), "depth": prev.depth.astype(np.float32), "ids": prev.ids,
               "motion_mask": prev.moving, "K": scene.K, "pose": poses[t]}
        if nxt is not None:
            out["flow"], out["flow_noc"], out["flow_occ"] = flow_gt(scene, t, prev, nxt)
        yield out
        prev = nxt


def generate_sequence(seed: int, index: int, frames: int, height: int = 128, width: int = 416) -> dict:
    """Whole sequence in memory (for tests and small previews).

    Returns dict: image (M, H, W, 3) uint8, depth (M, H, W) float32, ids (M, H, W) int32,
    motion_mask (M, H, W) bool, flow (M-1, H, W, 2) float32, flow_noc / flow_occ (M-1, H, W) bool,
    poses (M, 4, 4) float64 camera-to-world (frame 0 = identity), K (3, 3) float64.
    """
    fr = list(iter_frames(seed, index, frames, height, width))
    out = {k: np.stack([f[k] for f in fr]) for k in ("image", "depth", "ids", "motion_mask")}
    for k in ("flow", "flow_noc", "flow_occ"):
        out[k] = np.stack([f[k] for f in fr[:-1]])
    out["poses"] = np.stack([f["pose"] for f in fr])
    out["K"] = fr[0]["K"]
    return out


def sequence_name(index: int) -> str:
    return f"seq_{index:04d}"


def write_sequence(out_dir, seed: int, index: int, frames: int, height: int, width: int) -> str:
    """Render sequence `index` into out_dir/seq_NNNN (via out_dir/.tmp_seq_NNNN + rename).

    Returns the status: "done" or "skipped" (already complete).
    """
    out_dir = Path(out_dir)
    name = sequence_name(index)
    final = out_dir / name
    if final.is_dir():
        return "skipped"
    tmp = out_dir / f".tmp_{name}"
    if tmp.exists():  # left by an interrupted run: start this sequence again
        shutil.rmtree(tmp)
    poses = []
    K = None
    for t, fr in enumerate(iter_frames(seed, index, frames, height, width)):
        stem = f"{t:06d}.png"
        write_image(tmp / "image" / stem, fr["image"])
        depth = np.where(fr["depth"] <= MAX_PNG_DEPTH, fr["depth"], 0.0)  # sky / far: no measurement
        write_depth_kitti(tmp / "depth" / stem, depth)
        write_mask(tmp / "motion_mask" / stem, fr["motion_mask"])
        if "flow" in fr:
            write_flow_kitti(tmp / "flow_occ" / stem, fr["flow"], fr["flow_occ"])
            write_flow_kitti(tmp / "flow_noc" / stem, fr["flow"], fr["flow_noc"])
        poses.append(fr["pose"])
        K = fr["K"]
    write_kitti_poses(tmp / "poses.txt", np.stack(poses))
    write_calib_K(tmp / "calib.txt", K)
    os.replace(tmp, final)
    return "done"


def _worker(args):
    out_dir, seed, index, frames, height, width = args
    t0 = time.perf_counter()
    status = write_sequence(out_dir, seed, index, frames, height, width)
    return index, status, time.perf_counter() - t0


def _check_config(out_dir: Path, config: dict) -> None:
    """Refuse to mix sequences made with other settings in one folder (resuming needs the same ones)."""
    path = out_dir / "synth_config.json"
    if path.exists():
        old = json.loads(path.read_text())
        keys = ("generator_version", "seed", "frames", "height", "width")
        if any(old.get(k) != config[k] for k in keys):
            raise GeoNetInputError(path, f"folder was generated with {', '.join(f'{k}={old.get(k)}' for k in keys)}",
                                   "Use a new --out folder, or the same settings to resume")
        config = {**config, "sequences": max(config["sequences"], old.get("sequences", 0))}
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(config, indent=1) + "\n")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m training.synth",
        description="Generate synthetic KITTI-like driving sequences with exact depth, optical-flow, "
                    "motion-mask and camera-pose ground truth, written in KITTI encodings. "
                    "Each sequence goes to OUT/seq_NNNN/ (image/, depth/, flow_occ/, flow_noc/, "
                    "motion_mask/, poses.txt, calib.txt); see docs/synthetic_data.md.",
        epilog="Deterministic: the same --seed gives identical files for any --workers. Resumable: "
               "complete sequences are skipped, interrupted ones (OUT/.tmp_seq_NNNN) are redone.")
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument("--sequences", type=int, default=4, help="number of sequences (default 4)")
    p.add_argument("--frames", type=int, default=100, help="frames per sequence, >= 2 (default 100)")
    p.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    p.add_argument("--height", type=int, default=128, help="image height (default 128)")
    p.add_argument("--width", type=int, default=416, help="image width (default 416)")
    p.add_argument("--workers", type=int, default=1, help="processes, one sequence each (default 1)")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames < 2 or args.sequences < 1 or args.height < 8 or args.width < 8 or args.workers < 1:
        raise SystemExit("error: need --frames >= 2, --sequences >= 1, --height/--width >= 8, --workers >= 1")
    from tqdm import tqdm

    args.out.mkdir(parents=True, exist_ok=True)
    try:
        _check_config(args.out, {"generator_version": GENERATOR_VERSION, "seed": args.seed, "frames": args.frames,
                                 "height": args.height, "width": args.width, "sequences": args.sequences})
    except GeoNetInputError as err:
        raise SystemExit(f"error: {err}") from None
    jobs = [(str(args.out), args.seed, i, args.frames, args.height, args.width) for i in range(args.sequences)]
    t0 = time.perf_counter()
    done = 0
    with tqdm(total=len(jobs), unit="seq", desc="synth") as bar:
        def record(status):
            nonlocal done
            done += status == "done"
            bar.update(1)
            bar.set_postfix(frames_per_s=f"{done * args.frames / (time.perf_counter() - t0):.1f}")

        if args.workers == 1:
            for job in jobs:
                record(_worker(job)[1])
        else:
            import multiprocessing as mp

            # spawn: no fork-inherited state; the pool is terminated if a worker fails.
            # One OpenCV thread per worker process: the workers are the parallelism.
            with mp.get_context("spawn").Pool(min(args.workers, len(jobs)), initializer=cv2.setNumThreads,
                                              initargs=(1,)) as pool:
                for _, status, _ in pool.imap_unordered(_worker, jobs):
                    record(status)
    print(f"{done} sequence(s) written, {len(jobs) - done} already complete, in {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
