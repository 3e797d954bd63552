"""Scene layout: a curving road, the ego trajectory, static dressing and traffic as yaw-oriented boxes.

World frame ("road world"): x right, y down, z forward, the ground is y = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from geonet_infer.conventions import kitti_like_K
from training.synth.textures import (
    M_BARK,
    M_BRICK,
    M_CONCRETE,
    M_FACADE_A,
    M_FACADE_B,
    M_FOLIAGE,
    M_GLASS,
    M_HILL,
    M_METAL,
    M_PAINT,
    M_TYRE,
    build_mip_atlas,
    make_tiles,
)

CAM_HEIGHT = 1.65  # KITTI camera height above the road, metres
NEAR = 0.05  # near plane used to clip boxes before projecting them

# Surface ids in the id image; box k has id BOX0 + k.
SKY, GROUND, BOX0 = 0, 1, 2

# Road layout in "road coordinates" d = x - x_centre(z) (metres, + = right).
LANE = 3.5
ROAD_HALF = 9.5  # 2 lanes each way (to 7 m) + parking strip
SIDEWALK_OUT = 13.5
EGO_LANE = 1.75
# (|d| from, |d| to, dashed, RGB): double centre line, dashed lane divider, solid edge line.
MARKINGS = (
    (0.07, 0.17, False, (0.85, 0.72, 0.25)),
    (3.44, 3.56, True, (0.88, 0.88, 0.85)),
    (6.90, 7.05, False, (0.88, 0.88, 0.85)),
)
DASH_LEN, DASH_PERIOD = 3.0, 9.0


Z_BEHIND, Z_AHEAD = 30.0, 170.0  # scenery from 30 m behind the start to 170 m past the end


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

    def place(self, z, d) -> np.ndarray:
        """[x, yaw] of the point at lateral offset d (metres, + = right) from the centre line at z."""
        return np.array([self.centre(z) + d, self.heading(z)])


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
        self.rows.append(
            (
                np.asarray(centre, float),
                float(yaw),
                np.asarray(half, float),
                int(mat),
                np.asarray(tint, float),
                np.asarray(texoff, float),
                int(group),
            )
        )

    def arrays(self):
        if not self.rows:
            z3 = np.zeros((0, 3))
            return z3, np.zeros(0), z3, np.zeros(0, int), z3, np.zeros((0, 2)), np.zeros(0, int)
        cols = list(zip(*self.rows))
        return (
            np.stack(cols[0]),
            np.array(cols[1]),
            np.stack(cols[2]),
            np.array(cols[3]),
            np.stack(cols[4]),
            np.stack(cols[5]),
            np.array(cols[6]),
        )


def _smooth_noise(rng: np.random.Generator, n: int, amp: float, periods=(40, 160)) -> np.ndarray:
    """(n,) sum of three random sinusoids with amplitude ~amp: smooth jitter over frames."""
    t = np.arange(n)
    out = np.zeros(n)
    for _ in range(3):
        out += amp / 3 * np.sin(2 * np.pi * t / rng.uniform(*periods) + rng.uniform(0, 2 * np.pi))
    return out


def make_trajectory(
    rng: np.random.Generator, frames: int, road: Road, speeds: tuple[float, float] = (0.4, 1.5)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ego camera at 10 Hz: speed in ``speeds`` (m/frame), following its lane on the curving road.

    A target speed below 0 is a stop (speed 0 until the next target): stop-and-go traffic draws
    its targets from a range that starts below 0.

    Returns:
        T_wc: (M, 4, 4) camera-to-road-world; z: (M,) road position; v: (M,) speed (m/frame).
    """
    lo, hi = speeds
    v = np.empty(frames)
    speed, target = rng.uniform(max(lo, 0.0) + 0.1, hi - 0.1), rng.uniform(lo, hi)
    for t in range(frames):
        if rng.random() < 1 / 30:
            target = rng.uniform(lo, hi)
        speed += np.clip(max(target, 0.0) - speed, -0.04, 0.04)  # ~0.4 m/s^2 at 10 Hz
        v[t] = speed
    z = np.concatenate([[0.0], np.cumsum(v[:-1])])
    drift = _smooth_noise(rng, frames, 0.25, (60, 200))
    if lo >= 0:  # always moving: the jitters run in frames (the scenes of the first generator)
        d = EGO_LANE + drift
        x = road.centre(z) + d
        # Heading from the path tangent (dx/dz of the road plus lane drift) plus small steering jitter.
        dxdz = np.gradient(x, z) if frames > 1 else np.tan(road.heading(z))
        yaw = np.arctan(dxdz) + np.radians(_smooth_noise(rng, frames, 0.3, (20, 80)))
        pitch = np.radians(_smooth_noise(rng, frames, 0.5, (15, 60)))
        roll = np.radians(_smooth_noise(rng, frames, 0.3, (15, 60)))
        y = -CAM_HEIGHT + _smooth_noise(rng, frames, 0.02, (10, 40))
    else:  # stops: the jitters run in distance travelled, so a stopped camera holds still
        v_mean = max(z[-1] / max(frames - 1, 1), 1e-6)
        tau = z / v_mean  # frames at the mean speed; constant while stopped
        frame = np.arange(frames)
        d = EGO_LANE + np.interp(tau, frame, drift)
        x = road.centre(z) + d
        dd_dz = np.interp(tau, frame, np.gradient(drift) if frames > 1 else np.zeros(frames)) / v_mean
        yaw = np.arctan(np.tan(road.heading(z)) + dd_dz)
        yaw += np.radians(np.interp(tau, frame, _smooth_noise(rng, frames, 0.3, (20, 80))))
        pitch = np.radians(np.interp(tau, frame, _smooth_noise(rng, frames, 0.5, (15, 60))))
        roll = np.radians(np.interp(tau, frame, _smooth_noise(rng, frames, 0.3, (15, 60))))
        y = -CAM_HEIGHT + np.interp(tau, frame, _smooth_noise(rng, frames, 0.02, (10, 40)))
    T = np.stack([make_T(rot_y(yaw[i]) @ rot_x(pitch[i]) @ rot_z(roll[i]), (x[i], y[i], z[i])) for i in range(frames)])
    return T, z, v


def _pastel(rng, lo=0.55, hi=1.0):
    return rng.uniform(lo, hi, 3)


CAR_COLOURS = np.array(
    [
        [0.9, 0.9, 0.9],
        [0.15, 0.15, 0.17],
        [0.6, 0.62, 0.65],
        [0.7, 0.1, 0.1],
        [0.15, 0.25, 0.6],
        [0.85, 0.8, 0.6],
        [0.2, 0.45, 0.25],
        [0.9, 0.6, 0.1],
    ]
)


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
    parts = (
        (0.0, 0.45 / 2, (0.45 * Wd, 0.45 / 2, 0.42 * L), M_TYRE, (1, 1, 1)),
        (0.0, 0.35 + (hb - 0.35) / 2, (Wd / 2, (hb - 0.35) / 2, L / 2), M_PAINT, tint),
        (-0.08 * L, hb + 0.23, (0.43 * Wd, 0.23, 0.27 * L), M_GLASS, tint),
    )
    for dz, yc, half, mat, tn in parts:
        c = origin + R @ np.array([0.0, -yc, dz])
        boxes.add(c, yaw0, half, mat, tn, off, group)


def make_scene(rng: np.random.Generator, frames: int, height: int, width: int, traffic: str = "light") -> Scene:
    """Random road, ego trajectory, static dressing, traffic, lighting and textures for one sequence.

    Everything is drawn from ``rng`` in a fixed order (the output of a seed depends on it).
    ``traffic``: "light" (the original scenes), "dense" or "queue" (see :data:`TRAFFIC`).
    """
    K = kitti_like_K(height, width)
    road = make_road(rng)
    T_wc, ego_z, _ = make_trajectory(rng, frames, road, TRAFFIC[traffic].ego_speed)
    z_end = ego_z[-1]
    boxes = _BoxList()
    for side in (-1, 1):
        _add_roadside(boxes, rng, road, side, -Z_BEHIND, z_end + Z_AHEAD)
        _add_street_furniture(boxes, rng, road, side, -Z_BEHIND, z_end + Z_AHEAD)
        _add_parked_cars(boxes, rng, road, side, -Z_BEHIND, z_end + Z_AHEAD)
        _add_backdrop(boxes, rng, road, side, z_end)
    group_T = _add_traffic(boxes, rng, road, ego_z, frames, TRAFFIC[traffic])

    (centre, yaw, half, mat, tint, texoff, group) = boxes.arrays()
    path = np.linalg.norm(T_wc[-1, :3, 3] - T_wc[0, :3, 3])
    sky_c = 0.5 * (T_wc[0, :3, 3] + T_wc[-1, :3, 3])
    sky_c[1] = -CAM_HEIGHT
    el, az = np.radians(rng.uniform(25, 60)), rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])
    atlas, y0 = build_mip_atlas(make_tiles(rng))
    ambient, gain = rng.uniform(0.35, 0.5), rng.uniform(0.9, 1.1)
    return Scene(
        K,
        height,
        width,
        road,
        T_wc,
        centre,
        yaw,
        half,
        mat,
        tint,
        texoff,
        group,
        group_T,
        sky_c,
        1000.0 + path,
        sun,
        ambient,
        gain,
        atlas,
        y0,
    )


def make_road(rng: np.random.Generator) -> Road:
    """Max heading ~20 deg, curvature radius >~ 70 m."""
    amp = np.array([rng.uniform(0, 14), rng.uniform(0, 3)])
    wl = np.array([rng.uniform(250, 600), rng.uniform(90, 200)])
    freq = 2 * np.pi / wl
    amp = np.minimum(amp, 0.18 / freq)
    return Road(amp, freq, rng.uniform(0, 2 * np.pi, 2))


def _add_roadside(boxes: _BoxList, rng, road: Road, side: int, z_lo: float, z_hi: float) -> None:
    """Segments of buildings, walls or open land (trees) along one side of the road."""
    place = road.place
    z = z_lo + rng.uniform(0, 10)
    while z < z_hi:
        seg_end = z + rng.uniform(40, 160)
        kind = rng.choice(["buildings", "wall", "open"], p=[0.6, 0.15, 0.25])
        while z < min(seg_end, z_hi):
            if kind == "buildings":
                z += _add_building(boxes, rng, road, side, z)
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


def _add_building(boxes: _BoxList, rng, road: Road, side: int, z: float) -> float:
    """One building starting at z; returns the road length it (and the gap after it) takes."""
    L, depth = rng.uniform(8, 30), rng.uniform(8, 20)
    h = 3.2 * rng.integers(2, 8) + rng.uniform(0, 1.0)
    setback = SIDEWALK_OUT + rng.uniform(0, 4) * (rng.random() < 0.5)
    zc = z + L / 2
    x, yaw = road.place(zc, side * (setback + depth / 2))
    mat = rng.choice([M_FACADE_A, M_FACADE_B, M_BRICK, M_CONCRETE], p=[0.35, 0.25, 0.25, 0.15])
    tint = _pastel(rng, 0.5, 1.0) if mat != M_BRICK else rng.uniform([0.8, 0.35, 0.25], [1.0, 0.6, 0.45])
    boxes.add((x, -h / 2, zc), yaw, (depth / 2, h / 2, L / 2), mat, tint)
    return L + (rng.uniform(0, 6) if rng.random() < 0.5 else 0.0)


def _add_street_furniture(boxes: _BoxList, rng, road: Road, side: int, z_lo: float, z_hi: float) -> None:
    """Poles (some with lamp arms or signs) and sidewalk trees."""
    place = road.place
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
            boxes.add(
                (x, -2.6, z),
                yaw,
                (0.4, 0.35, 0.03),
                M_PAINT,
                rng.choice([(1.0, 0.25, 0.2), (0.2, 0.4, 0.9), (0.95, 0.85, 0.2), (0.9, 0.9, 0.9)]),
            )
        if rng.random() < 0.35:
            _add_tree(boxes, rng, place, z + rng.uniform(4, 8), side * 11.6)
        z += rng.uniform(15, 35)


def _add_parked_cars(boxes: _BoxList, rng, road: Road, side: int, z_lo: float, z_hi: float) -> None:
    """Parked cars on the parking strip, in runs."""
    z = z_lo + rng.uniform(0, 15)
    while z < z_hi:
        run_end = z + rng.uniform(10, 60)
        if rng.random() < 0.55:
            while z < run_end:
                x, yaw = road.place(z, side * rng.uniform(8.2, 8.4))
                add_car(boxes, rng, (x, z), yaw + rng.uniform(-0.03, 0.03))
                z += rng.uniform(5.0, 9.0)
        z = run_end + rng.uniform(5, 40)


def _add_backdrop(boxes: _BoxList, rng, road: Road, side: int, z_end: float) -> None:
    """Far backdrop (hills, distant blocks) 60-250 m out, world-fixed."""
    z = -100.0
    while z < z_end + 500:
        L, h = rng.uniform(30, 150), rng.uniform(8, 50)
        dist = rng.uniform(60, 250)
        x, yaw = road.place(z + L / 2, side * (dist + 10))
        mat = rng.choice([M_HILL, M_CONCRETE, M_FACADE_A])
        tint = np.array([0.8, 0.85, 0.95]) * rng.uniform(0.8, 1.1)
        boxes.add(
            (x, -h / 2 + 0.5, z + L / 2),
            yaw + rng.uniform(-0.3, 0.3),
            (10, h / 2, L / 2),
            mat,
            tint,
            rng.uniform(0, 20, 2),
        )
        z += L * rng.uniform(0.5, 1.2)


@dataclass(frozen=True)
class Traffic:
    """How close and how big the moving vehicles are."""

    lead_prob: float  # a lead vehicle in the ego lane
    lead_gap: tuple[float, float]  # its distance ahead (m), before the slow drift
    lead_min: float  # never closer than this (m)
    lane_skip: float  # probability that a lane has no traffic at all
    speed: tuple[float, float]  # |speed| in m per frame
    spacing: tuple[float, float]  # gap to the next vehicle in a lane (m)
    truck_prob: float  # a vehicle is a truck (cab + box, 7-12 m long, up to 3.8 m high)
    ego_speed: tuple[float, float] = (0.4, 1.5)  # the camera's target speeds, m per frame (below 0: a stop)
    one_way: bool = False  # every lane drives the camera's way (a multi-lane road), none towards it


TRAFFIC = {
    # The original scenes: the lead car 14-35 m ahead, a few cars per lane, no trucks.
    "light": Traffic(0.7, (14, 35), 9.0, 0.25, (0.4, 1.8), (12, 60), 0.0),
    # Queues: vehicles 5-15 m ahead and beside the camera, a third of them trucks, slow. Real
    # traffic fills much of the view with near vehicle sides and backs, which light traffic never does.
    "dense": Traffic(0.95, (5, 15), 4.5, 0.05, (0.1, 1.0), (8, 20), 0.3),
    # Stop-and-go: dense traffic on a one-way road, the camera stopping (a third of its target
    # speeds are stops) and crawling, the vehicles beside it crawling on at their own pace. Still
    # and slow cameras among moving vehicles, which the other kinds never show (issue 53).
    "queue": Traffic(0.95, (5, 15), 4.5, 0.0, (0.0, 0.6), (8, 20), 0.3, (-0.3, 0.6), True),
}


def add_truck(boxes: _BoxList, rng, group: int) -> None:
    """A truck as 3 boxes in its group's frame (wheels, cab, cargo box), bottom on the ground.

    The group origin is the truck's rear (a car's is its centre), so a lead truck is never
    closer than the lead gap however long it is.
    """
    L, Wd = rng.uniform(7.0, 12.0), rng.uniform(2.3, 2.5)
    hc, hb = rng.uniform(2.6, 3.1), rng.uniform(3.0, 3.8)  # cab and cargo-box tops
    tint = CAR_COLOURS[rng.integers(len(CAR_COLOURS))] * rng.uniform(0.85, 1.1)
    box_tint = rng.uniform([0.7, 0.7, 0.7], [1.1, 1.1, 1.1])
    off = rng.uniform(0, 5, 2)
    cab = 2.2
    parts = (  # (z of the box centre from the rear, y of its centre, half sizes, material, tint)
        (L / 2, 0.5, (0.45 * Wd, 0.5, 0.45 * L), M_TYRE, (1, 1, 1)),
        (L - cab / 2, 0.9 + (hc - 0.9) / 2, (Wd / 2, (hc - 0.9) / 2, cab / 2), M_PAINT, tint),
        ((L - cab) / 2, 0.9 + (hb - 0.9) / 2, (Wd / 2, (hb - 0.9) / 2, (L - cab) / 2), M_PAINT, box_tint),
    )
    for dz, yc, half, mat, tn in parts:
        boxes.add(np.array([0.0, -yc, dz]), 0.0, half, mat, tn, off, group)


def _add_traffic(
    boxes: _BoxList, rng, road: Road, ego_z: np.ndarray, frames: int, traffic: Traffic = TRAFFIC["light"]
) -> np.ndarray:
    """Moving vehicles, each a rigid group of boxes; returns group_T (G, M, 4, 4) group-to-world per frame."""
    groups = []
    t_idx = np.arange(frames)
    z_end = ego_z[-1]

    def group_poses(zs, d):
        x = road.centre(zs) + d
        yaw = road.heading(zs)
        return np.stack([make_T(rot_y(yaw[i]), (x[i], 0.0, zs[i])) for i in range(frames)])

    if rng.random() < traffic.lead_prob:  # lead vehicle in the ego lane
        gap = rng.uniform(*traffic.lead_gap) + _smooth_noise(rng, frames, rng.uniform(0, 10), (40, 150))
        groups.append(group_poses(ego_z + np.maximum(gap, traffic.lead_min), EGO_LANE))
    for d, direction in ((LANE + EGO_LANE, 1), (-EGO_LANE, -1), (-(LANE + EGO_LANE), -1)):
        direction = 1 if traffic.one_way else direction
        if rng.random() < traffic.lane_skip:
            continue
        speed = direction * rng.uniform(*traffic.speed)
        # Spread vehicles over the stretch of road they will cross during the sequence.
        span_lo, span_hi = (-60, z_end + 120) if direction > 0 else (0, z_end + 120 + abs(speed) * frames)
        z0 = span_lo + rng.uniform(0, 15)
        while z0 < span_hi:
            groups.append(group_poses(z0 + speed * t_idx, d))
            z0 += rng.uniform(*traffic.spacing)
    for g in range(len(groups)):
        # light traffic draws no truck lottery, so its scenes stay those of earlier versions
        if traffic.truck_prob > 0 and rng.random() < traffic.truck_prob:
            add_truck(boxes, rng, group=g)
        else:
            add_car(boxes, rng, None, 0.0, group=g)
    return np.stack(groups) if groups else np.zeros((0, frames, 4, 4))


def _add_tree(boxes: _BoxList, rng, place, z, d):
    x, yaw = place(z, d)
    h = rng.uniform(1.8, 3.0)
    boxes.add((x, -h / 2, z), yaw, (0.15, h / 2, 0.15), M_BARK, (1, 1, 1), rng.uniform(0, 5, 2))
    r = rng.uniform(1.0, 2.2)
    boxes.add(
        (x, -h - r * 0.8, z),
        yaw + rng.uniform(-0.5, 0.5),
        (r, r * 0.8, r),
        M_FOLIAGE,
        rng.uniform([0.7, 0.8, 0.6], [1.0, 1.1, 0.9]),
        rng.uniform(0, 5, 2),
    )
