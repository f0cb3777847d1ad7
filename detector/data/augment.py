"""Colour normalisation of the network input and the augmentations both stages train with: the frame-level roll,
jitter and colour change of stage 1 (:func:`augment`), and the colour modes (:data:`COLOUR_MODES`: ``light``,
``camera`` and its variants, :func:`camera_colour`, colours as another camera would give them; ``none``: no colour
input) that both stages offer."""

from __future__ import annotations

import numpy as np
from scipy.stats import rankdata


def normalised_colour(rgb: np.ndarray, normalisation: dict) -> np.ndarray:
    """Network colour input: ``(rgb - rgb_mean) / rgb_std``; zeros for a network without colour input
    (``normalisation["colour"] == "none"``); for ``"rank"`` each channel's rank among the n points given
    (:func:`colour_ranks`); for ``"grey_world"`` the colours first balanced over the n points (:func:`grey_world`).
    rgb: (n,3) in [0, 1]; normalisation: {"rgb_mean", "rgb_std"[, "colour"]} (:func:`input_normalisation`). Returns
    (n,3) float32."""
    mode = normalisation.get("colour")
    if mode == "none":
        return np.zeros(np.shape(rgb), np.float32)
    if mode == "rank":
        return colour_ranks(rgb)
    if mode == "grey_world":
        rgb = grey_world(rgb)
    return ((rgb - normalisation["rgb_mean"]) / normalisation["rgb_std"]).astype(np.float32)


def grey_world(rgb: np.ndarray) -> np.ndarray:
    """Grey-world balance: each channel divided by its mean over the n points and scaled so that the mean is 0.5,
    then clipped to [0, 2] (a channel whose mean is below 1e-3 becomes 0). Unchanged by a gain on any channel
    (exposure, white balance) short of clipping; hues relative to the scene's mean are kept. rgb: (n,3). Returns
    (n,3) float64 in [0, 2]."""
    rgb = np.asarray(rgb, np.float64)
    mean = rgb.mean(axis=0) if len(rgb) else np.ones(3)
    return np.where(mean > 1e-3, np.clip(rgb * (0.5 / np.maximum(mean, 1e-3)), 0.0, 2.0), 0.0)


def colour_ranks(rgb: np.ndarray) -> np.ndarray:
    """Each colour channel replaced by its rank among the n points, scaled to zero mean and unit variance
    (``((rank + 0.5) / n - 0.5) * sqrt(12)``, equal values sharing their mean rank). Unchanged by any increasing
    change of a channel (exposure, white balance, gamma, contrast) short of clipping. rgb: (n,3). Returns (n,3)
    float32 in (-sqrt(3), sqrt(3))."""
    rgb = np.asarray(rgb)
    if len(rgb) == 0:
        return np.zeros(np.shape(rgb), np.float32)
    ranks = rankdata(rgb, method="average", axis=0) - 0.5  # 0.5 .. n - 0.5
    return ((ranks / len(rgb) - 0.5) * np.sqrt(12.0)).astype(np.float32)


#: The modes that change colour with camera_colour, and its options for each: the tone curve (``tone``) and the grey
#: and colourless draws (``grey``).
CAMERA_MODES = {"camera": {"tone": False, "grey": True}, "camera_tone": {"tone": True, "grey": True},
                "camera_rgb": {"tone": False, "grey": False}, "rank": {"tone": True, "grey": True},
                "grey_world": {"tone": False, "grey": True}, "grey_world_rgb": {"tone": False, "grey": False}}

#: The modes whose network sees the colours changed before normalising, and how (the checkpoint's
#: ``normalisation["colour"]``): colour ranks, grey-world balance, or none at all.
INPUT_COLOUR = {"none": "none", "rank": "rank", "grey_world": "grey_world", "grey_world_rgb": "grey_world"}

#: The colour input of both stages' training: "light" (colour with a small gain and noise), "camera" (colour changed as
#: another camera would give it: camera_colour), "camera_tone" ("camera" plus the camera's tone curve: contrast and
#: colour saturation, camera_colour with ``tone``), "camera_rgb" ("camera" without its grey and colourless draws:
#: every input keeps three colour channels, camera_colour with ``grey`` False), "rank" ("camera_tone"'s changes, and
#: the network sees each channel as its rank among the crop's points in stage 2, the sampled frame's in stage 1:
#: colour_ranks, the same whatever the camera's exposure, white balance, gamma or contrast), "grey_world" ("camera"'s
#: changes, and the network sees the colours balanced by grey_world over the same points: the same whatever the
#: camera's exposure and white balance), "grey_world_rgb" ("grey_world" without the grey and colourless draws, as
#: "camera_rgb") or "none" (no colour: the network sees geometry only, in training and at inference, whatever
#: camera gives the frame).
COLOUR_MODES = ("light", *CAMERA_MODES, "none")

#: COLOUR_MODES as a config error names them.
COLOUR_MODES_TEXT = ", ".join(COLOUR_MODES[:-1]) + " or " + COLOUR_MODES[-1]

#: camera_colour's ranges: exposure gain, per-channel white-balance gain, gamma, and the chances of a grey crop and
#: of one without colour.
EXPOSURE = (0.5, 1.6)

WHITE_BALANCE = 0.15

GAMMA = (0.6, 1.6)

P_GREY, P_NO_COLOUR = 0.1, 0.05

#: camera_colour's tone curve (``tone``): contrast about the crop's mean luminance and colour saturation about each
#: point's luminance, gains drawn log-uniformly. Real cameras' own tone curves make prints more contrasted and more
#: saturated than a render (more clipped channels): on the ycbv_real frames 39 % of the gelatin box's points have a
#: channel at 0.98 or more, 1.2 % in a simulated capture of it (RESULTS.md, bench/colour_stats.py).
CONTRAST = (0.7, 1.6)

SATURATION = (0.6, 1.8)


def camera_colour(rgb: np.ndarray, rng: np.random.Generator, tone: bool = False, grey: bool = True) -> np.ndarray:
    """Colours as another camera might give them: ``(rgb * exposure * white_balance) ** gamma`` plus 2 % noise, with
    the exposure and gamma drawn log-uniformly from :data:`EXPOSURE` and :data:`GAMMA`; with ``grey``, with chance
    :data:`P_GREY` the crop is grey and with :data:`P_NO_COLOUR` all zeros (a depth-only input; without ``grey``
    those draws keep their colours, which are otherwise drawn as with it). With ``tone`` the
    colours also get a tone curve after the gamma: a contrast gain (:data:`CONTRAST`) about their mean luminance and a
    saturation gain (:data:`SATURATION`) about each point's luminance, clipped to [0, 1] (without ``tone`` the draws
    are those of before it existed).

    rgb: (n,3) in [0, 1]. Returns (n,3) float32 in [0, 1].
    """
    u = rng.random()  # drawn with or without ``grey``: the later draws are the same either way
    if grey and u < P_NO_COLOUR:
        return np.zeros_like(rgb, dtype=np.float32)
    gain = np.exp(rng.uniform(*np.log(EXPOSURE))) * rng.uniform(1 - WHITE_BALANCE, 1 + WHITE_BALANCE, 3)
    out = np.clip(np.asarray(rgb, np.float64) * gain, 0.0, 1.0) ** np.exp(rng.uniform(*np.log(GAMMA)))
    if tone:
        contrast, saturation = np.exp(rng.uniform(*np.log(CONTRAST))), np.exp(rng.uniform(*np.log(SATURATION)))
        lum = out.mean(axis=1, keepdims=True)
        out = lum + (out - lum) * saturation
        mean = out.mean()
        out = np.clip(mean + (out - mean) * contrast, 0.0, 1.0)
    if grey and u < P_NO_COLOUR + P_GREY:
        out = np.repeat(out.mean(1, keepdims=True), 3, axis=1)
    return np.clip(out + rng.normal(0.0, 0.02, out.shape), 0.0, 1.0).astype(np.float32)


#: Colour normalisation of the network input; the label file stores colour in [0, 1].
NORMALISATION: dict[str, float] = {"rgb_mean": 0.5, "rgb_std": 0.25}


def input_normalisation(colour: str) -> dict:
    """The input normalisation a stage trained with colour mode ``colour`` (:data:`COLOUR_MODES`) keeps in its
    checkpoint: :data:`NORMALISATION`, plus ``"colour": "none"`` for a network without colour input (its colour
    channels are zero in training and at inference), ``"colour": "rank"`` for one that sees colour ranks
    (:func:`colour_ranks`) or ``"colour": "grey_world"`` for one that sees balanced colours (:func:`grey_world`;
    modes ``grey_world`` and ``grey_world_rgb``): :data:`INPUT_COLOUR`."""
    return {**NORMALISATION, "colour": INPUT_COLOUR[colour]} if colour in INPUT_COLOUR else dict(NORMALISATION)


def reads_colour(normalisation: dict | None) -> bool:
    """Whether a network with this input normalisation (:func:`input_normalisation`, as a checkpoint keeps it; None:
    none stored) takes colour input: all but ``"colour": "none"``."""
    return (normalisation or {}).get("colour") != "none"

#: Augmentation strengths (metres, radians, colour units in [0, 1]).
JITTER_SIGMA = 0.002

JITTER_CLIP = 0.005

ROTATION_MAX = np.deg2rad(15.0)

BRIGHTNESS = 0.15

COLOUR_SIGMA = 0.02


def normalise_features(features: np.ndarray, normalisation: dict[str, float] | None = None) -> np.ndarray:
    """Network input from label-file features: colour centred and scaled, xyz and normals unchanged.

    features: (N, 9) float32 [X, Y, Z, R, G, B, Nx, Ny, Nz] with colour in [0, 1]. Returns (N, 9) float32.
    """
    norm = NORMALISATION if normalisation is None else normalisation
    out = np.array(features, dtype=np.float32, copy=True)
    out[:, 3:6] = normalised_colour(out[:, 3:6], norm)
    return out


def rot_z(angle: float) -> np.ndarray:
    """Rotation about the camera's optical (z) axis by ``angle`` radians: (3, 3) float32."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=np.float32)


def augment(features: np.ndarray, control_points: np.ndarray, rng: np.random.Generator, colour: str = "light"
            ) -> tuple[np.ndarray, np.ndarray]:
    """Light augmentation: a small roll about the camera axis (points, normals and labels alike), xyz jitter,
    and a colour change: ``colour`` "light" is a brightness gain of +-15 % and colour noise, "camera" the whole
    frame's colours as another camera would give them (:func:`detector.data.augment.camera_colour`: exposure, white
    balance, gamma, sometimes grey or none; "camera_tone", "camera_rgb", "rank" and "grey_world" its variants,
    :data:`CAMERA_MODES`; the network input of "rank" and "grey_world" is :func:`colour_ranks` or :func:`grey_world`
    of the changed colours, by :func:`normalise_features`),
    "none" leaves colour as it is (the network does not see it).

    features: (N, 9) float32, colour in [0, 1]; control_points: (N, 9, 3) float32 metres (zeros = background).
    Returns new arrays of the same shapes; background control points stay zero.
    """
    R = rot_z(rng.uniform(-ROTATION_MAX, ROTATION_MAX))
    out = np.array(features, dtype=np.float32, copy=True)
    out[:, 0:3] = out[:, 0:3] @ R.T
    out[:, 6:9] = out[:, 6:9] @ R.T
    cps = (control_points @ R.T).astype(np.float32)
    jitter = np.clip(rng.normal(0.0, JITTER_SIGMA, (len(out), 3)), -JITTER_CLIP, JITTER_CLIP)
    out[:, 0:3] += jitter.astype(np.float32)
    if colour in CAMERA_MODES:
        out[:, 3:6] = camera_colour(out[:, 3:6], rng, **CAMERA_MODES[colour])
    elif colour == "light":
        gain = rng.uniform(1.0 - BRIGHTNESS, 1.0 + BRIGHTNESS)
        out[:, 3:6] = np.clip(out[:, 3:6] * gain + rng.normal(0.0, COLOUR_SIGMA, (len(out), 3)), 0.0, 1.0)
    return out, cps
