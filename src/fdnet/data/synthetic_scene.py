"""The synthetic route's world and how each condition draws it (:mod:`fdnet.data.synthetic`
renders the frames): the street's buildings, trees and lamps drawn from a seed, the condition
looks (sky, foliage, snow, night lights) and the panoramas each frame is a crop of.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fdnet.data.images import GREY_WEIGHTS

CONDITIONS = ("summer", "autumn", "winter", "night")

# Vertical layout, in units of the frame height (0 = top).
_GROUND_Y = 0.64  # where buildings, trees and lamps stand
_ROAD_TOP = 0.74  # grass verge above this, road below
_DASH_Y = (0.86, 0.885)
HILL_SPEED = 0.3  # parallax: hills move at 30 % of the street's speed
CLOUD_SPEED = 0.08


# --------------------------------------------------------------------------- the scene
@dataclass
class Building:
    x0: float
    width: float
    height: float
    facade: np.ndarray  # RGB
    roof: str  # "flat" or "pitched"
    roof_colour: np.ndarray
    window_cols: int
    window_rows: int
    window_fill: float  # fraction of each grid cell that is glass
    lit: np.ndarray  # (rows, cols) bool: lit at night


@dataclass
class Tree:
    x: float
    trunk_height: float
    crown_w: float
    crown_h: float
    evergreen: bool
    autumn_colour: np.ndarray


@dataclass
class Lamp:
    x: float
    height: float


@dataclass
class Scene:
    """Everything that makes a place a place; the same in every condition."""

    length: float  # in units of the frame height
    buildings: list[Building] = field(default_factory=list)
    trees: list[Tree] = field(default_factory=list)
    lamps: list[Lamp] = field(default_factory=list)
    hill_profile: np.ndarray | None = None  # skyline height (units) per hill-panorama column
    dashes: list[tuple[float, float]] = field(default_factory=list)


_FACADES = np.array(
    [
        [0.80, 0.72, 0.60],
        [0.70, 0.35, 0.28],
        [0.85, 0.85, 0.80],
        [0.55, 0.60, 0.65],
        [0.90, 0.80, 0.45],
        [0.45, 0.50, 0.40],
        [0.75, 0.55, 0.45],
        [0.60, 0.45, 0.55],
    ],
    dtype=np.float32,
)
_ROOFS = np.array([[0.35, 0.15, 0.12], [0.25, 0.25, 0.28], [0.45, 0.30, 0.20], [0.20, 0.30, 0.25]], dtype=np.float32)
_AUTUMN_LEAVES = np.array(
    [[0.85, 0.45, 0.10], [0.75, 0.20, 0.10], [0.90, 0.75, 0.20], [0.60, 0.35, 0.15]], dtype=np.float32
)


def make_scene(length: float, seed: int) -> Scene:
    """Place structures along ``length`` units of street, deterministically from ``seed``."""
    rng = np.random.default_rng([seed, 1])
    scene = Scene(length=length)
    x = 0.05
    while x < length:
        kind = rng.choice(["building", "tree", "lamp", "gap"], p=[0.45, 0.3, 0.15, 0.1])
        if kind == "building":
            w = float(rng.uniform(0.3, 1.1))
            rows, cols = int(rng.integers(1, 6)), int(rng.integers(1, 7))
            scene.buildings.append(
                Building(
                    x0=x,
                    width=w,
                    height=float(rng.uniform(0.15, 0.5)),
                    facade=_FACADES[rng.integers(len(_FACADES))] * float(rng.uniform(0.85, 1.1)),
                    roof=str(rng.choice(["flat", "pitched"], p=[0.55, 0.45])),
                    roof_colour=_ROOFS[rng.integers(len(_ROOFS))],
                    window_cols=cols,
                    window_rows=rows,
                    window_fill=float(rng.uniform(0.35, 0.7)),
                    lit=rng.random((rows, cols)) < rng.uniform(0.3, 0.9),
                )
            )
            x += w + float(rng.uniform(0.02, 0.2))
        elif kind == "tree":
            cw = float(rng.uniform(0.12, 0.35))
            scene.trees.append(
                Tree(
                    x=x + cw / 2,
                    trunk_height=float(rng.uniform(0.05, 0.15)),
                    crown_w=cw,
                    crown_h=float(rng.uniform(0.12, 0.35)),
                    evergreen=bool(rng.random() < 0.35),
                    autumn_colour=_AUTUMN_LEAVES[rng.integers(len(_AUTUMN_LEAVES))],
                )
            )
            x += cw + float(rng.uniform(0.02, 0.15))
        elif kind == "lamp":
            scene.lamps.append(Lamp(x=x + 0.02, height=float(rng.uniform(0.28, 0.4))))
            x += float(rng.uniform(0.1, 0.3))
        else:
            x += float(rng.uniform(0.2, 0.6))
    # Road markings: dashes of varied length and spacing (they move with the street). Their own
    # random stream, so a longer route keeps the same places at the start.
    rng = np.random.default_rng([seed, 4])
    x = 0.0
    while x < length:
        d = float(rng.uniform(0.15, 0.35))
        scene.dashes.append((x, x + d))
        x += d + float(rng.uniform(0.15, 0.5))
    return scene


def hill_profile(columns: int, px: int, seed: int) -> np.ndarray:
    """Skyline height above the ground line (units) for each hill-panorama column: a few
    sinusoids plus a smoothed random walk, so every stretch of skyline has its own shape."""
    rng = np.random.default_rng([seed, 2])
    u = np.arange(columns) / px
    h = np.full(columns, 0.16)
    for period, amp in ((3.1, 0.06), (1.3, 0.035), (0.55, 0.015)):
        h += amp * np.sin(2 * np.pi * u / (period * rng.uniform(0.8, 1.2)) + rng.uniform(0, 2 * np.pi))
    # Random walk knots every 1/8 unit, so the skyline at a place does not depend on the route length.
    knots = int(np.ceil(u[-1] * 8)) + 2 if columns else 2
    walk = np.cumsum(rng.normal(0, 0.02, knots))
    walk -= np.convolve(walk, np.ones(9) / 9, mode="same")
    h += np.interp(u * 8, np.arange(knots), walk)
    return np.clip(h, 0.03, 0.3)


# --------------------------------------------------------------------------- condition looks
@dataclass
class _Look:
    sky_top: tuple
    sky_horizon: tuple
    hills: tuple
    grass: tuple
    road: tuple
    dash: tuple
    facade_gain: float  # multiplies facade colours
    saturation: float  # 1 keeps colour, 0 makes it grey
    glass: tuple  # unlit window colour
    leaves: str  # "green", "autumn", "bare"
    snow: bool
    night: bool
    clouds: int  # clouds per 10 units
    cloud_colour: tuple
    haze: float  # blend toward the horizon colour
    noise: float  # sensor noise sigma
    lateral_offset: float  # camera offset along the street (units), per condition
    exposure_sigma: float


LOOKS = {
    "summer": _Look(
        (0.30, 0.55, 0.95),
        (0.70, 0.85, 1.00),
        (0.25, 0.48, 0.20),
        (0.30, 0.62, 0.20),
        (0.36, 0.36, 0.38),
        (0.95, 0.95, 0.90),
        1.0,
        1.0,
        (0.20, 0.28, 0.40),
        "green",
        False,
        False,
        4,
        (1.0, 1.0, 1.0),
        0.0,
        0.012,
        0.0,
        0.05,
    ),
    "autumn": _Look(
        (0.50, 0.58, 0.72),
        (0.85, 0.80, 0.70),
        (0.50, 0.38, 0.18),
        (0.50, 0.38, 0.16),
        (0.30, 0.30, 0.31),
        (0.85, 0.85, 0.80),
        0.9,
        0.9,
        (0.18, 0.22, 0.28),
        "autumn",
        False,
        False,
        9,
        (0.80, 0.80, 0.82),
        0.12,
        0.015,
        0.08,
        0.08,
    ),
    "winter": _Look(
        (0.68, 0.70, 0.74),
        (0.80, 0.81, 0.83),
        (0.92, 0.93, 0.96),
        (0.94, 0.95, 0.97),
        (0.58, 0.58, 0.62),
        (0.80, 0.80, 0.82),
        0.8,
        0.45,
        (0.25, 0.27, 0.30),
        "bare",
        True,
        False,
        0,
        (0.75, 0.76, 0.78),
        0.18,
        0.02,
        -0.1,
        0.08,
    ),
    # Night: lit by street lighting, so outlines stay (shared with day) but are brighter than the
    # near-black sky, the reverse of daytime, and lit windows invert the day's dark glass; with
    # the condition's lateral offset this defeats patch-normalised pixel comparison (SAD R@1
    # night->summer, frames 200:300, tolerance 1: 0.22 with a dark 0.1 ambient, lighter sky and
    # 0.05 offset; 0.05 with these settings, chance 0.03).
    "night": _Look(
        (0.005, 0.005, 0.02),
        (0.02, 0.02, 0.05),
        (0.14, 0.155, 0.17),
        (0.125, 0.155, 0.125),
        (0.155, 0.155, 0.17),
        (0.23, 0.23, 0.22),
        0.7,
        0.3,
        (0.02, 0.02, 0.03),
        "green",
        False,
        True,
        0,
        (0.0, 0.0, 0.0),
        0.0,
        0.03,
        0.12,
        0.15,
    ),
}
_LIT_WINDOW = np.array([1.0, 0.82, 0.45], dtype=np.float32)
_LAMP_LIGHT = np.array([1.0, 0.9, 0.6], dtype=np.float32)


def _desaturate(colour, s: float) -> np.ndarray:
    c = np.asarray(colour, dtype=np.float32)
    # a colour's luminance as a float32 dot product: the scenes' pixels were generated so
    grey = float(c @ np.array(GREY_WEIGHTS, dtype=np.float32))
    return grey + s * (c - grey)


# --------------------------------------------------------------------------- panoramas
class _Canvas:
    """An RGB panorama with helpers that fill shapes on slices (no per-pixel Python loops)."""

    def __init__(self, height: int, width: int, px: int):
        self.rgb = np.zeros((height, width, 3), dtype=np.float32)
        self.alpha = np.zeros((height, width), dtype=np.float32)
        self.light = np.zeros((height, width, 3), dtype=np.float32)  # emitted light (night)
        self.px = px

    def _span(self, a: float, b: float, limit: int) -> tuple[int, int]:
        return max(int(round(a * self.px)), 0), min(int(round(b * self.px)), limit)

    def rect(self, x0, x1, y0, y1, colour) -> None:
        c0, c1 = self._span(x0, x1, self.rgb.shape[1])
        r0, r1 = self._span(y0, y1, self.rgb.shape[0])
        if c1 > c0 and r1 > r0:
            self.rgb[r0:r1, c0:c1] = colour
            self.alpha[r0:r1, c0:c1] = 1.0

    def mask(self, x0, x1, y0, y1, fn, colour) -> None:
        """Fill where ``fn(u, v)`` is True; u, v in [0, 1) across the box."""
        c0, c1 = self._span(x0, x1, self.rgb.shape[1])
        r0, r1 = self._span(y0, y1, self.rgb.shape[0])
        if c1 <= c0 or r1 <= r0:
            return
        v, u = np.mgrid[r0:r1, c0:c1].astype(np.float32)
        u = (u - x0 * self.px) / max((x1 - x0) * self.px, 1e-6)
        v = (v - y0 * self.px) / max((y1 - y0) * self.px, 1e-6)
        m = fn(u, v)
        region = self.rgb[r0:r1, c0:c1]
        if np.ndim(colour) == 3:
            region[m] = colour[m]
        else:
            region[m] = colour
        self.alpha[r0:r1, c0:c1][m] = 1.0

    def glow(self, x, y, radius, colour, strength) -> None:
        """Add a Gaussian blob of emitted light centred at (x, y) units."""
        c0, c1 = self._span(x - 3 * radius, x + 3 * radius, self.rgb.shape[1])
        r0, r1 = self._span(y - 3 * radius, y + 3 * radius, self.rgb.shape[0])
        if c1 <= c0 or r1 <= r0:
            return
        v, u = np.mgrid[r0:r1, c0:c1].astype(np.float32) / self.px
        g = np.exp(-((u - x) ** 2 + (v - y) ** 2) / (2 * radius**2)) * strength
        self.light[r0:r1, c0:c1] += g[..., None] * colour


def draw_street(scene: Scene, look: _Look, height: int, width: int, px: int, rng, seed: int) -> _Canvas:
    """Ground, road, buildings, trees and lamps for one condition, as one long panorama."""
    cv = _Canvas(height, width, px)
    sat = look.saturation
    # Ground: grass verge, road, dashes; a faint fixed texture so the ground is not flat.
    cv.rect(0, scene.length, _GROUND_Y, _ROAD_TOP, _desaturate(look.grass, sat))
    cv.rect(0, scene.length, _ROAD_TOP, 1.01, _desaturate(look.road, sat))
    for a, b in scene.dashes:
        cv.rect(a, b, *_DASH_Y, _desaturate(look.dash, sat))
    # Drawn column by column (transposed) so it does not depend on the route length either.
    texture = np.random.default_rng([seed, 3]).normal(0, 1, (width, height)).T.astype(np.float32)
    g0 = int(_GROUND_Y * px)
    scale = 0.02 if not look.night else 0.005
    cv.rgb[g0:] += scale * texture[g0:, :, None]
    if look.leaves == "autumn":  # fallen leaves on the verge: a condition-specific nuisance
        r0, r1 = int(_GROUND_Y * px), int(_ROAD_TOP * px)
        spots = rng.random((r1 - r0, width)) < 0.08
        cv.rgb[r0:r1][spots] = _AUTUMN_LEAVES[rng.integers(len(_AUTUMN_LEAVES), size=int(spots.sum()))]
    _draw_buildings(cv, scene, look, width, height, px)
    _draw_trees(cv, scene, look)
    _draw_lamps(cv, scene, look)
    return cv


def _draw_buildings(cv: _Canvas, scene: Scene, look: _Look, width: int, height: int, px: int) -> None:
    """Facades, window grids (lit at night), roofs and snow on them."""
    sat = look.saturation
    for b in scene.buildings:
        top = _GROUND_Y - b.height
        facade = _desaturate(b.facade * look.facade_gain, sat)
        cv.rect(b.x0, b.x0 + b.width, top, _GROUND_Y, facade)
        # Window grid: each grid cell holds one window of relative size window_fill.
        margin = 0.04
        wx0, wx1, wy0, wy1 = b.x0 + margin, b.x0 + b.width - margin, top + margin, _GROUND_Y - margin
        if wx1 - wx0 > 0.05 and wy1 - wy0 > 0.05:
            cols, rows, fill = b.window_cols, b.window_rows, b.window_fill

            def windows(u, v, cols=cols, rows=rows, fill=fill):
                fu, fv = (u * cols) % 1.0, (v * rows) % 1.0
                return (
                    (fu > (1 - fill) / 2)
                    & (fu < (1 + fill) / 2)
                    & (fv > (1 - fill) / 2)
                    & (fv < (1 + fill) / 2)
                    & (u >= 0)
                    & (u < 1)
                    & (v >= 0)
                    & (v < 1)
                )

            glass = np.asarray(look.glass, dtype=np.float32)
            if look.night:
                # Which windows are lit is part of the place (the same every night).
                def colour_of(u, v, b=b, glass=glass):
                    col = np.clip((u * b.window_cols).astype(int), 0, b.window_cols - 1)
                    row = np.clip((v * b.window_rows).astype(int), 0, b.window_rows - 1)
                    on = b.lit[row, col]
                    out = np.where(on[..., None], _LIT_WINDOW, glass)
                    return out.astype(np.float32)

                c0, c1 = cv._span(wx0, wx1, width)
                r0, r1 = cv._span(wy0, wy1, height)
                if c1 > c0 and r1 > r0:
                    v, u = np.mgrid[r0:r1, c0:c1].astype(np.float32)
                    u = (u - wx0 * px) / ((wx1 - wx0) * px)
                    v = (v - wy0 * px) / ((wy1 - wy0) * px)
                    cv.mask(wx0, wx1, wy0, wy1, windows, colour_of(u, v))
            else:
                cv.mask(wx0, wx1, wy0, wy1, windows, glass)
        roof = _desaturate(b.roof_colour * look.facade_gain, sat)
        snow = np.array([0.95, 0.96, 0.98], dtype=np.float32)
        if b.roof == "pitched":
            rh = min(0.12, b.width * 0.35)
            cv.mask(b.x0 - 0.02, b.x0 + b.width + 0.02, top - rh, top, lambda u, v: v >= np.abs(2 * u - 1), roof)
            if look.snow:
                cv.mask(
                    b.x0 - 0.02,
                    b.x0 + b.width + 0.02,
                    top - rh,
                    top,
                    lambda u, v: (v >= np.abs(2 * u - 1)) & (v < np.abs(2 * u - 1) + 0.35),
                    snow,
                )
        else:
            cv.rect(b.x0 - 0.01, b.x0 + b.width + 0.01, top - 0.025, top, roof)
            if look.snow:
                cv.rect(b.x0 - 0.01, b.x0 + b.width + 0.01, top - 0.045, top - 0.025, snow)


def _draw_trees(cv: _Canvas, scene: Scene, look: _Look) -> None:
    """Trunks and crowns (evergreen cones, bare branches or leaves of the season)."""
    sat = look.saturation
    trunk = _desaturate((0.30, 0.22, 0.15), sat) * (look.facade_gain if look.night else 1.0)
    for t in scene.trees:
        crown_bottom = _GROUND_Y - t.trunk_height
        cv.rect(t.x - 0.012, t.x + 0.012, crown_bottom - t.crown_h * 0.5, _GROUND_Y, trunk)
        x0, x1, y0 = t.x - t.crown_w / 2, t.x + t.crown_w / 2, crown_bottom - t.crown_h
        if t.evergreen:
            shape = lambda u, v: v >= np.abs(2 * u - 1) * 0.9  # noqa: E731 - a cone
            colour = _desaturate((0.10, 0.30, 0.15), sat) * (look.facade_gain if look.night else 1.0)
            cv.mask(x0, x1, y0, crown_bottom, shape, colour)
            if look.snow:  # snow lies on the upper side of the cone's branches
                cv.mask(
                    x0,
                    x1,
                    y0,
                    crown_bottom,
                    lambda u, v: (v >= np.abs(2 * u - 1) * 0.9) & ((v * 4) % 1.0 < 0.35),
                    np.array([0.93, 0.94, 0.97], dtype=np.float32),
                )
        elif look.leaves == "bare":
            # Bare branches: a few thin rays from the trunk top, fixed by the tree's position.
            def branches(u, v, seed=int(t.x * 1000)):
                angles = np.random.default_rng(seed).uniform(-1.2, 1.2, 6)
                du, dv = u - 0.5, 1.0 - v
                m = np.zeros(u.shape, dtype=bool)
                for a in angles:
                    m |= (np.abs(du * np.cos(a) - dv * np.sin(a)) < 0.05) & (du * np.sin(a) + dv * np.cos(a) > 0)
                return m & (((u - 0.5) / 0.5) ** 2 + ((v - 0.5) / 0.5) ** 2 <= 1)

            cv.mask(x0, x1, y0, crown_bottom, branches, trunk)
        else:
            base = t.autumn_colour if look.leaves == "autumn" and not look.night else (0.22, 0.50, 0.18)
            colour = _desaturate(base, sat) * (look.facade_gain if look.night else 1.0)
            cv.mask(x0, x1, y0, crown_bottom, lambda u, v: (u - 0.5) ** 2 + (v - 0.5) ** 2 <= 0.25, colour)


def _draw_lamps(cv: _Canvas, scene: Scene, look: _Look) -> None:
    """Lamp posts, and at night their light and the light spilling from lit windows."""
    sat = look.saturation
    pole = _desaturate((0.30, 0.30, 0.32), sat) * (look.facade_gain if look.night else 1.0)
    for lamp in scene.lamps:
        top = _GROUND_Y - lamp.height
        cv.rect(lamp.x - 0.008, lamp.x + 0.008, top, _GROUND_Y, pole)
        cv.rect(lamp.x - 0.008, lamp.x + 0.05, top, top + 0.015, pole)
        head = _LAMP_LIGHT if look.night else _desaturate((0.75, 0.75, 0.70), sat)
        cv.rect(lamp.x + 0.025, lamp.x + 0.055, top + 0.012, top + 0.03, head)
        if look.night:
            cv.glow(lamp.x + 0.04, top + 0.025, 0.035, _LAMP_LIGHT, 0.9)
            cv.glow(lamp.x + 0.04, (_ROAD_TOP + 1.0) / 2, 0.09, _LAMP_LIGHT, 0.35)  # pool of light
    if look.night:
        # Lit windows spill a little light around them.
        for b in scene.buildings:
            if b.lit.any():
                cv.glow(
                    b.x0 + b.width / 2,
                    _GROUND_Y - b.height / 2,
                    max(b.width, b.height) / 2.5,
                    _LIT_WINDOW,
                    0.08 * float(b.lit.mean()),
                )


def sky_and_hills(
    scene: Scene, look: _Look, height: int, hill_width: int, px: int, profile: np.ndarray, rng
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sky gradient (H, 3), cloud/star layer (H, Wc, 4) and hills panorama (H, Wh, 4)."""
    y = np.arange(height, dtype=np.float32)[:, None] / height
    t = np.clip(y / _GROUND_Y, 0, 1)
    sky = (1 - t) * np.asarray(look.sky_top, np.float32) + t * np.asarray(look.sky_horizon, np.float32)

    cloud_w = int(scene.length * CLOUD_SPEED * px) + 4 * px
    clouds = np.zeros((height, cloud_w, 4), dtype=np.float32)
    if look.night:
        stars = rng.random((height, cloud_w)) < 0.004
        stars[int(_GROUND_Y * height * 0.8) :] = False
        clouds[stars] = (0.7, 0.7, 0.8, 1.0)
    n_clouds = int(look.clouds * cloud_w / px / 10) + (1 if look.clouds else 0)
    v, u = np.mgrid[0:height, 0:cloud_w].astype(np.float32) / px
    for _ in range(n_clouds):
        cx, cy = rng.uniform(0, cloud_w / px), rng.uniform(0.05, 0.3)
        rx, ry = rng.uniform(0.15, 0.5), rng.uniform(0.04, 0.09)
        d = ((u - cx) / rx) ** 2 + ((v - cy) / ry) ** 2
        a = np.clip(1.2 - d, 0, 1) * 0.9
        clouds[..., :3] = clouds[..., :3] * (1 - a[..., None]) + a[..., None] * np.asarray(look.cloud_colour)
        clouds[..., 3] = np.maximum(clouds[..., 3], a)

    hills = np.zeros((height, hill_width, 4), dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)[:, None] / px
    skyline = _GROUND_Y - profile[None, :]
    inside = rows >= skyline
    shade = np.clip((rows - skyline) / 0.25, 0, 1)[..., None]  # lighter near the ridge
    colour = _desaturate(look.hills, look.saturation)
    hill_rgb = colour * (1.0 - 0.25 * shade) if not look.night else colour * np.ones_like(shade)
    hills[..., :3] = np.where(inside[..., None], hill_rgb, 0)
    hills[..., 3] = inside
    return sky, clouds, hills
