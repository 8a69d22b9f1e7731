"""Photo-textured panoramas with natural-image statistics for the KITTI and MAV demo worlds.

A panorama here is an equirectangular BGR uint8 image (width // 2, width) at infinity, the input
of `rotlearn.data.demo.synth.render` (column j is longitude 2 pi j / width about world y, row i
latitude pi ((i + 0.5) / height - 0.5) towards world +y, i.e. down; the horizon is the middle
row).

- `street_panorama`: a street-level outdoor scene: a sky of soft 1/f clouds over facades built
  from real photographs (brick, stone, plaster; tinted, shaded, with windows and posters, of
  varied sizes, occluding each other), trees and poles in front, and a ground plane of gravel,
  asphalt and grass seen in perspective (texture detail shrinking towards the horizon).
- `room_panorama`: an indoor scene that looks different: darker, walls of plaster and wooden
  panels, framed pictures, doors, ceiling lights and a tiled floor, under uneven lighting.

The textures are real photographs bundled inside the scikit-image wheel (`skimage/data/*`), all
CC0 or public domain (the list, with their sources, is in data/README.md); they are read from the
installed package's folder, never downloaded. scikit-image is needed only here, imported lazily:
`pip install rotlearn[data]`. Everything is drawn from the caller's numpy Generator, so a seed
gives the same panorama.
"""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "PHOTOS",
    "TEXTURES",
    "bundled_images",
    "crop",
    "periodic_component",
    "pink_noise",
    "room_panorama",
    "street_panorama",
]

# Bundled, CC0 or public-domain files of skimage/data (licences: data/README.md).
TEXTURES = ("brick.png", "grass.png", "gravel.png")  # 512 x 512 gray
PHOTOS = ("camera.png", "coffee.png", "chelsea.png", "astronaut.png", "rocket.jpg")


@functools.cache
def bundled_images() -> dict[str, np.ndarray]:
    """The `TEXTURES` (gray) and `PHOTOS` (BGR; camera.png as gray BGR) of skimage/data as float32
    in [0, 1], read once from the installed scikit-image package's own folder (bundled files
    only: nothing is fetched).

    Raises:
        ModuleNotFoundError: scikit-image is not installed (`pip install rotlearn[data]`).
        FileNotFoundError: a bundled file is missing or unreadable in the installed wheel.
    """
    try:
        import skimage.data
    except ImportError as error:
        raise ModuleNotFoundError(
            "the photo-textured demo worlds need scikit-image's bundled images: "
            "pip install rotlearn[data]"
        ) from error
    folder = Path(skimage.data.__file__).parent
    images = {}
    for name in TEXTURES + PHOTOS:
        path = folder / name
        image = cv2.imread(str(path), cv2.IMREAD_COLOR if name in PHOTOS else cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(
                f"{path}: missing or unreadable; the demo worlds need scikit-image's bundled "
                f"data files (scikit-image {getattr(skimage, '__version__', '?')})"
            )
        image = image.astype(np.float32) / 255.0
        images[name] = periodic_component(image) if name in TEXTURES else image
    return images


def periodic_component(image: np.ndarray) -> np.ndarray:
    """The periodic component of a gray image (Moisan's periodic + smooth decomposition): the
    image less the smooth field that its wrap-around edge jumps induce, so that it tiles without
    seams. (h, w) float32 in, (h, w) float32 out, clipped to [0, 1]."""
    h, w = image.shape
    jumps = np.zeros_like(image, dtype=np.float64)
    jumps[0, :] += image[-1, :] - image[0, :]
    jumps[-1, :] += image[0, :] - image[-1, :]
    jumps[:, 0] += image[:, -1] - image[:, 0]
    jumps[:, -1] += image[:, 0] - image[:, -1]
    cy = 2 * np.cos(2 * np.pi * np.arange(h) / h)[:, None]
    cx = 2 * np.cos(2 * np.pi * np.arange(w) / w)[None, :]
    denominator = cy + cx - 4.0
    denominator[0, 0] = 1.0
    smooth = np.fft.fft2(jumps) / denominator
    smooth[0, 0] = 0.0
    return np.clip(image - np.real(np.fft.ifft2(smooth)), 0, 1).astype(np.float32)


# ---- noise ---------------------------------------------------------------------------------------


def pink_noise(rng: np.random.Generator, height: int, width: int, exponent: float = 2.0):
    """Gaussian noise (height, width) float32, zero mean, unit variance, with power spectrum
    ~ 1 / f ** exponent (2: the spectrum of natural images), periodic in both axes (the
    panorama's longitude wraps without a seam)."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.rfftfreq(width)[None, :]
    f = np.maximum(np.hypot(fx, fy), 1.0 / max(height, width))
    shape = (height, width // 2 + 1)
    spectrum = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) * f ** (-exponent / 2)
    spectrum[0, 0] = 0.0
    noise = np.fft.irfft2(spectrum, s=(height, width)).astype(np.float32)
    return noise / max(float(noise.std()), 1e-12)


# ---- painting helpers (longitude wraps) ----------------------------------------------------------


def _paste(canvas: np.ndarray, patch: np.ndarray, x: int, y: int, alpha=None) -> None:
    """Composite `patch` (h, w, 3) onto `canvas` (H, W, 3) float32 at column x, row y; columns
    wrap round the panorama, rows are clipped. `alpha` (h, w) in [0, 1] or None (opaque)."""
    height, width = canvas.shape[:2]
    h, w = patch.shape[:2]
    y0, y1 = max(y, 0), min(y + h, height)
    if y1 <= y0 or w <= 0:
        return
    patch = patch[y0 - y : y1 - y]
    cols = (x + np.arange(min(w, width))) % width
    patch = patch[:, : len(cols)]
    if alpha is None:
        canvas[y0:y1, cols] = patch
    else:
        a = alpha[y0 - y : y1 - y, : len(cols), None]
        canvas[y0:y1, cols] = a * patch + (1.0 - a) * canvas[y0:y1, cols]


def crop(rng: np.random.Generator, image: np.ndarray, h: int, w: int, scale: float) -> np.ndarray:
    """A random (h, w[, C]) view of `image` tiled (wrapping), sampled at `scale` source pixels
    per output pixel (area-filtered when shrinking)."""
    sh, sw = max(1, round(h * scale)), max(1, round(w * scale))
    reps = (-(-sh // image.shape[0]) + 1, -(-sw // image.shape[1]) + 1) + (1,) * (image.ndim - 2)
    tiled = np.tile(image, reps)
    y0, x0 = rng.integers(image.shape[0]), rng.integers(image.shape[1])
    region = tiled[y0 : y0 + sh, x0 : x0 + sw]
    interp = cv2.INTER_AREA if scale > 1 else cv2.INTER_LINEAR
    return cv2.resize(region, (w, h), interpolation=interp)


def _gray_tinted(texture: np.ndarray, colour, contrast: float) -> np.ndarray:
    """(h, w) gray texture in [0, 1] -> (h, w, 3) BGR: `colour` (BGR, [0, 1]) modulated by the
    texture around its mean with the given contrast."""
    t = 1.0 + contrast * (texture - texture.mean())
    return t[..., None] * np.asarray(colour, np.float32)


def _photo_tinted(photo: np.ndarray, colour, saturation: float) -> np.ndarray:
    """BGR photo with its saturation scaled and a colour cast (multiplicative)."""
    gray = photo.mean(axis=-1, keepdims=True)
    return (gray + saturation * (photo - gray)) * np.asarray(colour, np.float32)


def _ramp(h: int, w: int, rng: np.random.Generator, strength: float) -> np.ndarray:
    """(h, w, 1) smooth shading: a random linear ramp across the patch, mean 1."""
    gx, gy = rng.uniform(-strength, strength, 2)
    u = np.linspace(-0.5, 0.5, w, dtype=np.float32)[None, :]
    v = np.linspace(-0.5, 0.5, h, dtype=np.float32)[:, None]
    return (1.0 + gx * u + gy * v)[..., None]


def _geometry(width: int) -> tuple[int, float, np.ndarray]:
    """(height, pixels per degree, latitude in radians of each row (height,))."""
    height = width // 2
    latitude = np.pi * ((np.arange(height) + 0.5) / height - 0.5)
    return height, width / 360.0, latitude


def _row(latitude_deg: float, height: int) -> int:
    """The panorama row of a latitude in degrees (positive: below the horizon)."""
    return round((latitude_deg / 180.0 + 0.5) * height - 0.5)


# ---- ground in perspective -----------------------------------------------------------------------


def _mip_sample(texture: np.ndarray, u: np.ndarray, v: np.ndarray, footprint: np.ndarray):
    """Sample a periodic texture (h, w[, C]) float32 at pixel coordinates (u, v) (any shape,
    wrapping), from the pyramid level matching `footprint` (texture pixels per output pixel):
    trilinear, so that detail fades without aliasing towards the horizon."""
    levels = [texture]
    while min(levels[-1].shape[:2]) > 4:
        levels.append(cv2.pyrDown(levels[-1], borderType=cv2.BORDER_WRAP))
    level = np.clip(np.log2(np.maximum(footprint, 1.0)), 0, len(levels) - 1).astype(np.float32)
    out = None
    for k, tex in enumerate(levels):
        weight = np.clip(1.0 - np.abs(level - k), 0.0, 1.0)
        if not weight.any():
            continue
        s = np.float32(2.0**-k)
        th, tw = tex.shape[:2]
        mx = np.mod(u * s, tw).astype(np.float32)
        my = np.mod(v * s, th).astype(np.float32)
        sample = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        if sample.ndim < weight.ndim + 1 and texture.ndim == 3:
            sample = sample.reshape(*weight.shape, -1)
        term = (weight[..., None] if texture.ndim == 3 else weight) * sample
        out = term if out is None else out + term
    return out


def _ground_coordinates(width: int, rows: np.ndarray, camera_height: float):
    """World ground-plane coordinates (X, Z) in metres (len(rows), width) of the panorama pixels
    of `rows` (below the horizon), and each pixel's footprint in metres."""
    _, _, latitude = _geometry(width)
    lat = latitude[rows][:, None]
    longitude = 2 * np.pi * np.arange(width)[None, :] / width
    distance = camera_height / np.tan(lat)
    X, Z = distance * np.sin(longitude), distance * np.cos(longitude)
    pixel = 2 * np.pi / width
    footprint = distance * pixel * np.maximum(1.0, distance / camera_height)
    return X.astype(np.float32), Z.astype(np.float32), footprint.astype(np.float32)


# ---- the street ----------------------------------------------------------------------------------

_FACADE_COLOURS = np.float32(  # BGR, [0, 1]: brick reds, sandstone, concrete, white, blue-grey
    [[0.35, 0.42, 0.70], [0.55, 0.68, 0.80], [0.62, 0.62, 0.62], [0.82, 0.85, 0.86],
     [0.70, 0.62, 0.52], [0.40, 0.50, 0.58], [0.30, 0.35, 0.55]]
)  # fmt: skip


def _sky(rng: np.random.Generator, height: int, width: int, latitude: np.ndarray) -> np.ndarray:
    """(height, width, 3) sky: blue overhead fading to a pale horizon, with soft 1/f clouds."""
    up = np.clip(-latitude / (np.pi / 2), 0, 1)[:, None, None]  # 0 at the horizon, 1 overhead
    zenith = np.float32([0.85, 0.55, 0.30]) * rng.uniform(0.85, 1.1)
    horizon = np.float32([0.95, 0.88, 0.82])
    sky = horizon + (zenith - horizon) * up**0.6
    cover = rng.uniform(0.3, 0.6)
    noise = pink_noise(rng, height, width, 2.4)
    clouds = np.clip((noise - (1.0 - 2 * cover)) / 1.2, 0, 1)[..., None]
    cloud_shade = 0.85 + 0.15 * np.tanh(noise)[..., None]
    return np.float32(sky * (1 - clouds) + np.float32([0.93, 0.93, 0.94]) * cloud_shade * clouds)


def _window_grid(rng, facade: np.ndarray, images) -> None:
    """Windows on a facade (h, w, 3) in place: a grid of dark glass panes reflecting a blurred
    photograph, each with a lighter frame."""
    h, w = facade.shape[:2]
    size = int(rng.integers(5, 14))  # window pitch in panorama pixels
    if h < 2 * size or w < 2 * size:
        return
    pane_w, pane_h = (
        max(2, int(size * rng.uniform(0.4, 0.7))),
        max(2, int(size * rng.uniform(0.5, 0.8))),
    )
    reflection = crop(rng, images[PHOTOS[rng.integers(len(PHOTOS))]], h, w, rng.uniform(0.5, 2))
    glass = 0.25 * cv2.GaussianBlur(reflection, (0, 0), 1.0) + np.float32([0.12, 0.1, 0.08])
    frame = np.float32(rng.uniform(0.7, 1.0, 3)) * facade.mean(axis=(0, 1)) * 1.2
    for y in range(size // 2, h - pane_h - 1, size + int(rng.integers(0, 3))):
        for x in range(size // 3, w - pane_w - 1, size):
            if rng.random() < 0.08:
                continue
            facade[y - 1 : y + pane_h + 1, x - 1 : x + pane_w + 1] = frame
            facade[y : y + pane_h, x : x + pane_w] = glass[y : y + pane_h, x : x + pane_w]


def _facade(rng: np.random.Generator, h: int, w: int, images) -> np.ndarray:
    """A building face (h, w, 3) float32: a tinted real texture (brick, gravel as stone, or a
    photograph as a painted wall), shaded by a ramp, sometimes with windows and a poster."""
    kind = rng.random()
    colour = _FACADE_COLOURS[rng.integers(len(_FACADE_COLOURS))] * rng.uniform(0.8, 1.15, 3)
    if kind < 0.45:
        texture = crop(rng, images["brick.png"], h, w, rng.uniform(0.4, 1.2))
        face = _gray_tinted(texture, colour, rng.uniform(0.8, 1.6))
    elif kind < 0.7:
        texture = crop(rng, images["gravel.png"], h, w, rng.uniform(0.6, 2.5))
        face = _gray_tinted(cv2.GaussianBlur(texture, (0, 0), 0.7), colour, rng.uniform(0.4, 1.0))
    else:
        photo = crop(rng, images[PHOTOS[rng.integers(len(PHOTOS))]], h, w, rng.uniform(0.6, 2.0))
        face = _photo_tinted(photo, colour * 1.2, rng.uniform(0.0, 0.4)) * 0.6 + 0.4 * colour
    if rng.random() < 0.7:
        _window_grid(rng, face, images)
    if rng.random() < 0.35 and h > 16 and w > 16:  # a poster or sign: a photograph
        ph, pw = int(h * rng.uniform(0.2, 0.45)), int(w * rng.uniform(0.2, 0.5))
        name = PHOTOS[rng.integers(len(PHOTOS))]
        poster = crop(
            rng,
            images[name],
            ph,
            pw,
            rng.uniform(0.5, 2.0) * images[name].shape[0] / max(ph, 1) / 2,
        )
        y, x = int(rng.integers(0, h - ph)), int(rng.integers(0, w - pw))
        face[y : y + ph, x : x + pw] = poster
    return face * _ramp(h, w, rng, 0.5)


def _tree(rng: np.random.Generator, h: int, w: int, images) -> tuple[np.ndarray, np.ndarray]:
    """A tree (h, w, 3) and its alpha (h, w): a crown of grass texture inside a soft 1/f-edged
    blob over a dark trunk."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    crown_h = 0.7 * h
    r = np.hypot((u - w / 2) / (w / 2), (v - crown_h / 2) / (crown_h / 2))
    edge = 0.25 * pink_noise(rng, h, w, 2.0)
    crown = np.clip((1.0 - r + edge) * 6.0, 0, 1)
    trunk = ((np.abs(u - w / 2) < max(1.0, w / 16)) & (v > crown_h * 0.6)).astype(np.float32)
    leaves = _gray_tinted(
        crop(rng, images["grass.png"], h, w, rng.uniform(0.5, 1.5)),
        np.float32([0.20, 0.45, 0.30]) * rng.uniform(0.7, 1.2, 3),
        1.5,
    )
    leaves *= _ramp(h, w, rng, 0.6)
    image = np.where(crown[..., None] > 0, leaves, np.float32([0.12, 0.18, 0.22]))
    return image, np.maximum(crown, trunk)


def _ground(rng: np.random.Generator, width: int, images) -> np.ndarray:
    """(height - horizon row, width, 3) ground below the horizon: an asphalt road (gravel, dark)
    along world z with dashed lane marks, pavements of brick, and grass and gravel verges,
    seen from 1.6 m in perspective."""
    height = width // 2
    rows = np.arange(height // 2, height)
    X, Z, footprint = _ground_coordinates(width, rows, camera_height=1.6)
    px_per_m = 96.0
    u, v = X * px_per_m, Z * px_per_m
    fp = footprint * px_per_m
    gravel = _mip_sample(images["gravel.png"], u, v, fp)
    grass = _mip_sample(images["grass.png"], u * 0.7, v * 0.7, fp * 0.7)
    brick = _mip_sample(images["brick.png"], u * 0.5, v * 0.5, fp * 0.5)
    patches = _mip_sample(pink_noise(rng, 256, 256, 2.0), u / 24, v / 24, fp / 24)
    half = rng.uniform(3.0, 5.0)
    fine = _mip_sample(images["gravel.png"], u * 4, v * 4, fp * 4)
    asphalt = (0.25 + 0.45 * (fine - 0.5))[..., None] * np.float32([1.0, 1.0, 1.02])
    pavement = (0.55 + 0.5 * (brick - 0.5))[..., None] * np.float32([0.85, 0.9, 0.95])
    verge_grass = (0.3 + 0.8 * (grass - 0.5))[..., None] * np.float32([0.25, 0.55, 0.40])
    verge_gravel = (0.5 + 0.7 * (gravel - 0.5))[..., None] * np.float32([0.6, 0.68, 0.72])
    verge = np.where((patches > 0.0)[..., None], verge_grass, verge_gravel)
    ax = np.abs(X)[..., None]
    ground = np.where(ax < half, asphalt, np.where(ax < half + 2.5, pavement, verge))
    dash = (np.abs(X) < 0.08) & (np.mod(Z, 6.0) < 3.0) & (Z > 3.0)
    ground[dash] = np.float32([0.85, 0.85, 0.85])
    # far away, everything blends into haze
    distance = np.hypot(X, Z)[..., None]
    haze = np.clip(distance / 400.0, 0, 1)
    return ground * (1 - haze) + np.float32([0.6, 0.6, 0.62]) * haze


def street_panorama(rng: np.random.Generator, width: int) -> np.ndarray:
    """Equirectangular BGR uint8 (width // 2, width) of a street (module docstring): sky, two rows
    of buildings (far ones first, nearer ones lower and occluding them), trees and poles, a
    perspective ground, and a soft 1/f illumination field over everything."""
    images = bundled_images()
    height, unit, latitude = _geometry(width)
    canvas = _sky(rng, height, width, latitude)
    horizon = height // 2
    canvas[horizon:] = _ground(rng, width, images)
    for layer, (base_deg, top_deg, count) in enumerate(((1.5, (8, 30), 14), (5.0, (12, 45), 10))):
        for _ in range(count):
            w = int(unit * rng.uniform(12, 60) * (1 + 0.4 * layer))
            top = _row(-rng.uniform(*top_deg), height)
            bottom = _row(base_deg + rng.uniform(-1, 1.5), height)
            face = _facade(rng, bottom - top, w, images)
            _paste(canvas, face * rng.uniform(0.75, 1.1), int(rng.integers(width)), top)
    for _ in range(int(rng.integers(6, 12))):  # trees in front
        h = int(unit * rng.uniform(15, 35))
        w = int(h * rng.uniform(0.5, 0.9))
        bottom = _row(rng.uniform(6, 12), height)
        tree, alpha = _tree(rng, h, w, images)
        _paste(canvas, tree, int(rng.integers(width)), bottom - h, alpha)
    for _ in range(int(rng.integers(8, 16))):  # lamp posts and sign poles
        bottom = _row(rng.uniform(4, 14), height)
        top = _row(-rng.uniform(5, 25), height)
        thick = int(rng.integers(1, 4))
        pole = np.full((bottom - top, thick, 3), rng.uniform(0.1, 0.35), np.float32)
        _paste(canvas, pole, int(rng.integers(width)), top)
    light = 1.0 + 0.12 * pink_noise(rng, height, width, 3.0)[..., None]
    return np.clip(255.0 * canvas * light, 0, 255).astype(np.uint8)


# ---- the room ------------------------------------------------------------------------------------


def room_panorama(rng: np.random.Generator, width: int) -> np.ndarray:
    """Equirectangular BGR uint8 (width // 2, width) of a room (module docstring): darker than
    the street, walls of plaster and wooden panels, framed photographs, doors and shelves, a
    ceiling with light panels, a tiled floor in perspective, under uneven lighting."""
    images = bundled_images()
    height, unit, _ = _geometry(width)
    canvas = np.zeros((height, width, 3), np.float32)
    # ceiling above 25 degrees up, floor below 20 degrees down, walls between
    ceiling_row, floor_row = _row(-25, height), _row(20, height)
    ceiling = _gray_tinted(
        crop(rng, images["gravel.png"], ceiling_row, width, 3.0), [0.55, 0.57, 0.6], 0.3
    )
    canvas[:ceiling_row] = ceiling
    for _ in range(int(rng.integers(4, 8))):  # ceiling lights
        w, h = int(unit * rng.uniform(5, 12)), int(unit * rng.uniform(3, 8))
        _paste(
            canvas,
            np.full((h, w, 3), 0.95, np.float32),
            int(rng.integers(width)),
            int(rng.integers(0, ceiling_row - h)),
        )
    x = 0
    while x < width:  # walls, one after another round the room
        w = int(unit * rng.uniform(25, 70))
        wall_colour = np.float32(rng.uniform(0.4, 0.75, 3)) * np.float32([0.9, 0.95, 1.0])
        if rng.random() < 0.5:
            texture = cv2.GaussianBlur(
                crop(rng, images["gravel.png"], floor_row - ceiling_row, w, 2.0), (0, 0), 1.5
            )
            wall = _gray_tinted(texture, wall_colour, 1.2)
        else:  # wooden panels: a photograph's grain stretched into boards
            source = images[("coffee.png", "chelsea.png")[rng.integers(2)]]
            grain = cv2.resize(
                crop(rng, source, 64, 64, 1.0),
                (w, floor_row - ceiling_row),
                interpolation=cv2.INTER_CUBIC,
            )
            wood = np.float32([0.20, 0.33, 0.50]) * rng.uniform(0.7, 1.2)
            wall = _photo_tinted(grain, wood / max(float(grain.mean()), 1e-3), 0.2)
            board = max(2, int(unit * rng.uniform(1.5, 4)))
            wall[:, ::board] *= 0.55
        wall *= _ramp(*wall.shape[:2], rng, 0.6)
        _paste(canvas, wall, x, ceiling_row)
        canvas[ceiling_row : ceiling_row + 2, np.arange(x, x + 2) % width] *= 0.5  # corner
        x += w
    for _ in range(int(rng.integers(14, 22))):  # framed pictures, doors, shelves, cabinets
        kind = rng.random()
        if kind < 0.55:
            ph, pw = int(unit * rng.uniform(8, 24)), int(unit * rng.uniform(8, 30))
            name = PHOTOS[rng.integers(len(PHOTOS))]
            scale = max(images[name].shape[:2]) / max(ph, pw) * rng.uniform(0.4, 1.0)
            picture = crop(rng, images[name], ph, pw, scale)
            border = max(2, int(unit * rng.uniform(0.5, 1.5)))
            frame = np.full(
                (ph + 2 * border, pw + 2 * border, 3), rng.uniform(0.05, 0.5), np.float32
            )
            frame[border:-border, border:-border] = picture
            y = _row(-rng.uniform(-5, 15), height) - ph // 2
            _paste(canvas, frame, int(rng.integers(width)), y)
        elif kind < 0.75:
            dw, dh = int(unit * rng.uniform(10, 16)), floor_row - _row(-8, height)
            wood = crop(rng, images["coffee.png"], dh, dw, rng.uniform(0.3, 0.8))
            door = _photo_tinted(wood, np.float32(rng.uniform(0.3, 0.7, 3)), 0.3)
            door *= _ramp(dh, dw, rng, 0.5)
            door[:, [0, 1, -2, -1]] *= 0.4
            _paste(canvas, door, int(rng.integers(width)), floor_row - dh)
        else:
            sw, sh = int(unit * rng.uniform(12, 30)), int(unit * rng.uniform(8, 20))
            name = PHOTOS[rng.integers(len(PHOTOS))]
            shelf = _photo_tinted(crop(rng, images[name], sh, sw, 1.0), [0.7, 0.7, 0.7], 0.5)
            shelf[:: max(3, sh // 4)] = 0.12
            shelf[:, [0, 1, -2, -1]] = 0.12
            _paste(canvas, shelf, int(rng.integers(width)), floor_row - sh)
    skirting = np.full((max(2, int(unit * 1.5)), width, 3), 0.25, np.float32)
    _paste(canvas, skirting, 0, floor_row - skirting.shape[0])
    rows = np.arange(floor_row, height)
    X, Z, footprint = _ground_coordinates(width, rows, camera_height=1.2)
    px_per_m = 160.0
    tiles = _mip_sample(images["brick.png"], X * px_per_m, Z * px_per_m, footprint * px_per_m)
    floor = (0.5 + 0.6 * (tiles - 0.5))[..., None] * np.float32([0.5, 0.55, 0.6])
    canvas[floor_row:] = floor
    light = np.exp(0.35 * pink_noise(rng, height, width, 3.0))[..., None]
    return np.clip(255.0 * 0.6 * canvas * light, 0, 255).astype(np.uint8)
