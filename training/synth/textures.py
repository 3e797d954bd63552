"""Material textures: tileable procedural tiles, their mip-mapped atlas and trilinear lookups (numpy + OpenCV)."""

from __future__ import annotations

import cv2
import numpy as np

# ---------------------------------------------------------------------------- materials
(
    M_ASPHALT,
    M_SIDEWALK,
    M_GRASS,
    M_FACADE_A,
    M_FACADE_B,
    M_BRICK,
    M_CONCRETE,
    M_PAINT,
    M_GLASS,
    M_TYRE,
    M_METAL,
    M_FOLIAGE,
    M_BARK,
    M_SKY,
    M_HILL,
) = range(15)
N_MAT = 15
TILE = 128  # texels per tile side
PAD = 2  # wrap padding around each tile in the atlas (bilinear needs 1)
LMAX = 6  # mip levels 0..6 (128 -> 2 texels)
# metres per texel; the sky is addressed directly in texels (1.0)
TEXEL_M = np.array(
    [0.03, 0.025, 0.02, 0.025, 0.025, 0.0125, 0.03, 0.02, 0.02, 0.02, 0.01, 0.015, 0.01, 1.0, 0.4], dtype=np.float32
)
SKY_REPEATS = 8  # sky tile repeats around the horizon
LOD_BIAS = 0.0  # added to every mip level: > 0 blurs textures slightly


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
    The tiles are drawn from ``rng`` in material order (the output depends on it).
    """
    yy, xx = np.mgrid[0:TILE, 0:TILE].astype(np.float32)
    tiles = np.zeros((N_MAT, TILE, TILE, 4), np.float32)
    for fill in (_ground_tiles, _building_tiles, _object_tiles, _sky_tiles):
        fill(rng, tiles, xx, yy)
    return tiles


def _ground_tiles(rng: np.random.Generator, tiles: np.ndarray, xx: np.ndarray, yy: np.ndarray) -> None:
    """Asphalt, sidewalk slabs, grass."""
    S = TILE
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


def _building_tiles(rng: np.random.Generator, tiles: np.ndarray, xx: np.ndarray, yy: np.ndarray) -> None:
    """Facades with windows, brick, concrete."""
    S = TILE
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


def _object_tiles(rng: np.random.Generator, tiles: np.ndarray, xx: np.ndarray, yy: np.ndarray) -> None:
    """Car paint, glass and tyres, metal poles, foliage and bark."""
    S = TILE
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


def _sky_tiles(rng: np.random.Generator, tiles: np.ndarray, xx: np.ndarray, yy: np.ndarray) -> None:
    """Sky with clouds and the far backdrop."""
    S = TILE
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
            atlas[y0[l] : y0[l] + s + 2 * PAD, x : x + s + 2 * PAD] = np.pad(
                t, ((PAD, PAD), (PAD, PAD), (0, 0)), mode="wrap"
            )
    return atlas, y0


def sample_atlas(
    atlas: np.ndarray, y0: np.ndarray, mat: np.ndarray, ta: np.ndarray, tb: np.ndarray, lod: np.ndarray
) -> np.ndarray:
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
