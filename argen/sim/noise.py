"""Depth-sensor models: lateral jitter, axial noise, disparity quantisation, holes, and the profile effects.

The axial model is Nguyen, Izadi & Lovell (2012), "Modeling Kinect Sensor Noise for Improved 3D
Reconstruction and Tracking":

    sigma_z(z, theta) = a + b (z - z0)^2 + 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2   [metres]

with a = 0.0012 m, b = 0.0019 1/m, z0 = 0.4 m (``NoiseConfig``) and theta the incidence angle.
Nguyen et al. measured this on real Kinect depth, so sigma_z is the *total* axial noise, disparity
quantisation included. :func:`apply_noise` therefore draws its Gaussian part with the reduced

    sigma_gauss = sqrt(max(sigma_z^2 - q(z)^2 / 12, 0)),   q(z) = z^2 * step / (fx * baseline),

where q(z) is the depth step between neighbouring disparity levels at depth z and q^2/12 the
variance of rounding to them, so that Gaussian + quantisation together have the model's sigma_z.

Beyond that per-pixel model, the sensor profiles (``argen/sensors/*.yaml``, ``--sensor``) switch on what
real depth sensors also do (see :func:`apply_noise` for the order):

- a spatially correlated axial error (structured light and stereo match 9 x 9 or 7 x 7 windows, so
  neighbouring pixels err together; Smisek et al. 2011 and Herrera et al. 2012 measured low-frequency
  depth distortions of a few mm on Kinect v1),
- a per-frame systematic error of depth scale and offset (Herrera et al. 2012: per-device scale and
  offset; Khoshelham & Elberink 2012: systematic errors after calibration),
- the IR shadow of the projector 7.5 cm beside the camera (stereo: the second camera's occlusion),
- mixed ("flying") pixels at depth discontinuities, and ToF multipath in concave regions (Sarbolandi
  et al. 2015), stereo edge fattening (Intel's D400 tuning guide),
- dropout at grazing angles, on dark surfaces and (stereo) on flat, textureless patches.

The kinect_v1 profile is calibrated with ``bench/bench_noise.py`` against a real LineMOD Kinect frame
measured the same way (distance of the depth to the ground-truth surface at 0.95-1.1 m: median 2.39 mm,
p95 6.14 mm; argen: 1.94 / 6.40 mm; BENCHMARKS.md). Sources of each profile's numbers are listed in its file.

All depths are metres, angles radians; a depth of 0 means "no measurement" on input and output.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.special import ndtr

from argen.config import NoiseConfig

# Coefficient of Nguyen et al.'s incidence-angle term, metres^1.5 (0.0001 / sqrt(z) metres).
ANGLE_COEF = 0.0001

_CACHE: dict[tuple, object] = {}  # rays and lateral tables per (image size, K / std)


def axial_sigma(z: np.ndarray | float, theta: np.ndarray | float, cfg: NoiseConfig) -> np.ndarray:
    """Total axial noise std of the sensor model (Nguyen et al. 2012).

    z: (...) depth, metres (> 0); theta: (...) incidence angle, radians, broadcastable with z
    (ignored unless ``cfg.angle_term``). Returns (...) sigma_z, metres, in the dtype of z
    (float64 for Python scalars). Angles are clipped just below pi/2 so the result stays finite.
    """
    z = np.asarray(z)
    if not np.issubdtype(z.dtype, np.floating):
        z = z.astype(np.float64)
    dz = z - z.dtype.type(cfg.axial_z0)
    sigma = z.dtype.type(cfg.axial_a) + z.dtype.type(cfg.axial_b) * dz * dz
    if cfg.angle_term:
        t = np.clip(np.asarray(theta, dtype=z.dtype), 0.0, np.pi / 2 - 1e-3)
        ratio = t / (z.dtype.type(np.pi / 2) - t)
        sigma = sigma + z.dtype.type(ANGLE_COEF) / np.sqrt(np.maximum(z, z.dtype.type(1e-6))) * ratio * ratio
    return sigma


def _unit_z_rays(h: int, w: int, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 rays K^-1 [u, v, 1] (z = 1) through the pixel centres; cached, read-only."""
    key = (h, w, tuple(np.asarray(K, dtype=np.float64).ravel().tolist()))
    rays = _CACHE.get(key)
    if rays is None:
        Kinv = np.linalg.inv(np.asarray(K, dtype=np.float64))
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        pix = np.stack([u, v, np.ones_like(u)], axis=-1)
        rays = (pix @ Kinv.T).astype(np.float32)
        rays.flags.writeable = False
        if len(_CACHE) > 8:
            _CACHE.clear()
        _CACHE[key] = rays
    return rays


def _check_inputs(depth: np.ndarray, K: np.ndarray) -> None:
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {depth.shape}")
    if np.shape(K) != (3, 3):
        raise ValueError(f"K must be (3, 3), got shape {np.shape(K)}")


def _one_sided_diff(w: np.ndarray, valid: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Finite difference of ``w`` along ``axis`` (1 = u, 0 = v), from the side with the smaller jump.

    Taking the smoother of the forward and backward difference keeps normals right next to depth
    discontinuities (the neighbour on the same surface is used). Returns ((H, W), ok (H, W)).
    """
    n = w.shape[axis]
    lo = [slice(None)] * 2
    hi = [slice(None)] * 2
    lo[axis], hi[axis] = slice(0, n - 1), slice(1, n)
    lo, hi = tuple(lo), tuple(hi)
    diff = w[hi] - w[lo]  # w[i+1] - w[i], stored at i
    ok = valid[hi] & valid[lo]
    pad_shape = list(w.shape)
    pad_shape[axis] = 1
    zero = np.zeros(pad_shape, dtype=w.dtype)
    no = np.zeros(pad_shape, dtype=bool)
    fwd, bwd = np.concatenate([diff, zero], axis), np.concatenate([zero, diff], axis)
    ok_f, ok_b = np.concatenate([ok, no], axis), np.concatenate([no, ok], axis)
    use_f = ok_f & (~ok_b | (np.abs(fwd) <= np.abs(bwd)))
    return np.where(use_f, fwd, bwd), ok_f | ok_b


def _normal_terms(z: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised away-facing normals m (3, H, W) and a validity mask (H, W) from depth z (H, W).

    Uses inverse depth w = 1/z, which is affine in (u, v) on any plane n . P + c = 0. For the plane
    through a pixel's back-projected point and its two chosen neighbours (one along u, one along v)
    its finite differences w_u, w_v are exact, and the plane normal is K^T (w_u, w_v, w - u w_u -
    v w_v) up to scale; this equals the cross product of the back-projected point differences, at
    scalar cost. m . K^-1 [u, v, 1] = w > 0, i.e. m points away from the camera.
    """
    h, w_ = z.shape
    valid = z > 0
    w = np.where(valid, np.float32(1.0) / np.where(valid, z, np.float32(1.0)), np.float32(0.0))
    wu, ok_u = _one_sided_diff(w, valid, axis=1)
    wv, ok_v = _one_sided_diff(w, valid, axis=0)
    u = np.arange(w_, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    g = (wu, wv, w - u * wu - v * wv)
    Kt = np.asarray(K, dtype=np.float32).T
    m = [Kt[i, 0] * g[0] + Kt[i, 1] * g[1] + Kt[i, 2] * g[2] if Kt[i].any() else np.zeros_like(w)
         for i in range(3)]
    return np.stack(m), valid & ok_u & ok_v


def normals_from_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame unit surface normals of a depth map, oriented toward the camera.

    depth: (H, W) metres, 0 = no measurement; K: (3, 3) pixels. Each pixel's normal is that of the
    plane through its back-projected point P = z K^-1 [u, v, 1] and one neighbour along u and one
    along v (the cross product of the finite differences of P), each neighbour taken on the side
    (forward or backward) with the smaller jump, so pixels next to a discontinuity get the normal
    of their own surface; computed exactly via inverse depth (see ``_normal_terms``). Returns
    (H, W, 3) float32, unit length with n . P < 0, and zeros where the pixel, or both of its
    neighbours along u or both along v, have no depth.
    """
    depth = np.asarray(depth)
    _check_inputs(depth, K)
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    m, good = _normal_terms(z, K)
    norm = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
    good &= norm > 0
    scale = np.where(good, np.float32(-1.0) / np.where(good, norm, np.float32(1.0)), np.float32(0.0))
    return np.moveaxis(m * scale, 0, -1).astype(np.float32)


def _ray_norm(h: int, w: int, K: np.ndarray) -> np.ndarray:
    """(H, W) float32 lengths of the rays K^-1 [u, v, 1] (cached)."""
    rays = _unit_z_rays(h, w, K)
    key = ("norm", h, w, tuple(np.asarray(K, dtype=np.float64).ravel().tolist()))
    r = _CACHE.get(key)
    if r is None:
        r = np.sqrt(np.einsum("hwc,hwc->hw", rays, rays))
        r.flags.writeable = False
        _CACHE[key] = r
    return r


def incidence_angle(depth: np.ndarray, K: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Angle between each pixel's viewing ray and its surface normal (0 = surface faces the camera).

    depth: (H, W) metres, 0 = no measurement; K: (3, 3) pixels; normals: (H, W, 3) camera-frame
    unit normals as from :func:`normals_from_depth`. Returns (H, W) float32 radians in [0, pi/2]
    (normals facing away count as pi/2); 0 where there is no depth or no normal (zero vector).
    """
    depth = np.asarray(depth)
    _check_inputs(depth, K)
    normals = np.asarray(normals, dtype=np.float32)
    rays = _unit_z_rays(*depth.shape, K)
    cos = -np.einsum("hwc,hwc->hw", normals, rays) / _ray_norm(*depth.shape, K)
    known = (depth > 0) & (np.einsum("hwc,hwc->hw", normals, normals) > 0.5)
    return np.where(known, np.arccos(np.clip(cos, 0.0, 1.0)), 0.0).astype(np.float32)


def _incidence_from_depth(z: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Same as ``incidence_angle(z, K, normals_from_depth(z, K))`` without the (H, W, 3) arrays.

    z: (H, W) float32 metres, 0 = none. With m from ``_normal_terms``, cos(theta) = w / (|m| |r|).
    """
    m, good = _normal_terms(z, K)
    norm = np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]) * _ray_norm(*z.shape, K)
    good &= norm > 0
    w = np.where(good, np.float32(1.0) / np.where(good, z, np.float32(1.0)), np.float32(0.0))
    cos = w / np.where(good, norm, np.float32(1.0))
    return np.where(good, np.arccos(np.clip(cos, 0.0, 1.0)), np.float32(0.0)).astype(np.float32)


_LATERAL_LEVELS = 1 << 16  # probability resolution of the discrete lateral shift


def _lateral_table(std_px: float, h: int, w: int) -> tuple[int, np.ndarray, np.ndarray]:
    """Cached lookup for :func:`_lateral_resample`: (pad, offsets (2^16,) int32, base (H, W) int32).

    The shift (dv, du) has independent rounded-Gaussian components, P(k) = Phi((k + 1/2) / std) -
    Phi((k - 1/2) / std); the joint distribution is tabulated at 2^-16 probability resolution (so
    shifts rarer than that, e.g. 3 px at std 0.5, are left out) as flat offsets dv * Wp + du into the
    image padded by ``pad`` pixels (width Wp); ``base`` holds each pixel's own padded flat index.
    """
    key = ("lateral", float(std_px), h, w)
    hit = _CACHE.get(key)
    if hit is None:
        pad = int(np.ceil(6.0 * std_px)) + 1
        k = np.arange(-pad, pad + 1)
        p1 = np.diff(ndtr((np.arange(-pad, pad + 2) - 0.5) / std_px))
        p2 = (p1[:, None] * p1[None, :]).ravel()
        cdf = np.cumsum(p2) / p2.sum()
        pick = np.searchsorted(cdf * _LATERAL_LEVELS, np.arange(_LATERAL_LEVELS) + 0.5)
        wp = w + 2 * pad
        dv, du = np.meshgrid(k, k, indexing="ij")
        offsets = (dv * wp + du).ravel()[np.minimum(pick, p2.size - 1)].astype(np.int32)
        rows = np.arange(pad, h + pad, dtype=np.int32)[:, None]
        base = rows * wp + np.arange(pad, w + pad, dtype=np.int32)[None, :]
        for a in (offsets, base):
            a.flags.writeable = False
        hit = (pad, offsets, base)
        if len(_CACHE) > 8:
            _CACHE.clear()
        _CACHE[key] = hit
    return hit


def _lateral_index(h: int, w: int, std_px: float, rng: np.random.Generator) -> tuple[int, np.ndarray]:
    """Source pixels of the lateral jitter: (pad, (H, W) int32 flat indices into the edge-padded image).

    Each pixel reads its nearest neighbour at its position shifted by a rounded N(0, std_px) in u
    and in v (see ``_lateral_table``); padding by edge replication clamps shifts at the border.
    """
    pad, offsets, base = _lateral_table(std_px, h, w)
    return pad, base + offsets[rng.integers(0, _LATERAL_LEVELS, (h, w), dtype=np.uint16)]


def _resample(a: np.ndarray, pad: int, idx: np.ndarray) -> np.ndarray:
    """a (H, W) read at the flat indices ``idx`` of its edge-padded copy; (H, W), dtype of a."""
    return np.take(np.pad(a, pad, mode="edge").ravel(), idx)


def _discontinuities(z: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) bool: pixels on either side of a jump > ``threshold`` metres to a 4-neighbour (both measured)."""
    valid = z > 0
    edge = np.zeros(z.shape, dtype=bool)
    jh = (np.abs(z[:, 1:] - z[:, :-1]) > threshold) & valid[:, 1:] & valid[:, :-1]
    jv = (np.abs(z[1:, :] - z[:-1, :]) > threshold) & valid[1:, :] & valid[:-1, :]
    edge[:, 1:] |= jh
    edge[:, :-1] |= jh
    edge[1:, :] |= jv
    edge[:-1, :] |= jv
    return edge


def correlated_field(h: int, w: int, radius_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 Gaussian field with unit std whose values are correlated over ``radius_px`` pixels: white
    noise averaged over (2r+1) x (2r+1) windows (a structured-light sensor matches such windows, so neighbouring
    pixels err together), rescaled to unit variance."""
    k = 2 * int(round(radius_px)) + 1
    white = rng.standard_normal((h, w), dtype=np.float32)
    if k <= 1:
        return white
    return cv2.blur(white, (k, k), borderType=cv2.BORDER_REFLECT) * np.float32(k)


def shadow_mask(z: np.ndarray, K: np.ndarray, baseline: float, tol: float = 0.01) -> np.ndarray:
    """(H, W) bool: pixels whose surface point the second viewpoint cannot see (IR shadow of a structured-light
    projector, left-right occlusion of a stereo pair). z: (H, W) float32 metres, 0 = none; the second viewpoint
    sits ``baseline`` metres along the camera's +x, rectified (same rows, same K). A point is hidden when another
    point of its row projects to the same column of the second view more than ``tol`` x its depth nearer."""
    h, w = z.shape
    valid = z > 0
    rows, cols = np.nonzero(valid)
    if len(rows) == 0:
        return np.zeros((h, w), bool)
    zz = z[rows, cols]
    # column in the second view: u' = u - fx * baseline / z (rectified pair, disparity fx b / z)
    up = np.rint(cols - float(K[0][0]) * baseline / zz).astype(np.int64)
    inside = (up >= 0) & (up < w)
    key = rows[inside] * w + up[inside]
    zbuf = np.full(h * w, np.inf, np.float32)
    np.minimum.at(zbuf, key, zz[inside])
    hidden = np.zeros(len(rows), bool)
    hidden[inside] = zz[inside] > zbuf[key] * (1.0 + tol)
    out = np.zeros((h, w), bool)
    out[rows[hidden], cols[hidden]] = True
    return out


def _minmax3(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3x3 neighbourhood min (of measured pixels) and max of z (H, W), float32."""
    big = np.where(z > 0, z, np.float32(np.inf))
    lo = cv2.erode(big, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    hi = cv2.dilate(z, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return np.where(np.isfinite(lo), lo, z).astype(np.float32), hi.astype(np.float32)


def _fatten(z: np.ndarray, edge: np.ndarray, px: int) -> np.ndarray:
    """Stereo edge fattening: within ``px`` of a discontinuity the nearer surface's depth spreads over the
    farther one (the matching window there is dominated by the nearer, textured side)."""
    k = 2 * px + 1
    big = np.where(z > 0, z, np.float32(np.inf))
    near = cv2.erode(big, np.ones((k, k), np.uint8), borderType=cv2.BORDER_REPLICATE)
    band = cv2.dilate(edge.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
    take = band & (z > 0) & np.isfinite(near)
    return np.where(take, near, z).astype(np.float32)


def _multipath(z: np.ndarray, gain: float, radius_px: float) -> np.ndarray:
    """ToF multipath: light scattered between surfaces that face each other (concave corners, an object on a
    table) arrives late, so depth reads long there. Approximated as ``gain`` x how far a pixel lies behind the
    mean depth of its neighbourhood (zero on planes and convex parts)."""
    k = 2 * int(round(radius_px)) + 1
    valid = (z > 0).astype(np.float32)
    s = cv2.blur(z * valid, (k, k), borderType=cv2.BORDER_REFLECT)
    n = cv2.blur(valid, (k, k), borderType=cv2.BORDER_REFLECT)
    mean = np.where(n > 0, s / np.maximum(n, np.float32(1e-6)), z)
    return np.where(z > 0, z + np.float32(gain) * np.maximum(z - mean, 0), 0).astype(np.float32)


def _luminance(rgb: np.ndarray) -> np.ndarray:
    rgb = np.asarray(rgb, np.float32) / np.float32(255.0)
    return rgb[..., 0] * np.float32(0.299) + rgb[..., 1] * np.float32(0.587) + rgb[..., 2] * np.float32(0.114)


def native_pitch(K: np.ndarray, cfg: NoiseConfig) -> float:
    """How many image pixels one of the depth sensor's own pixels spans: ``fx / cfg.native_fx`` when that is
    above 1.01 (a depth image registered to a narrower colour camera, e.g. YCB-Video's Xtion at fx 1067 against
    the depth camera's ~572), else 1 (the image is at the sensor's pitch, or ``native_fx`` is 0: unknown)."""
    if cfg.native_fx <= 0:
        return 1.0
    s = float(K[0][0]) / float(cfg.native_fx)
    return s if s > 1.01 else 1.0


def _pitch_grid(n_hi: int, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Sampling along one image axis at ``s`` image pixels per sensor pixel. Returns (down, up): ``down`` (n_lo,)
    the image pixel nearest each sensor pixel's centre; ``up`` (n_hi,) the sensor pixel each image pixel lies in."""
    n_lo = max(int(round(n_hi / s)), 1)
    down = np.clip(np.rint((np.arange(n_lo) + 0.5) * s - 0.5), 0, n_hi - 1).astype(np.intp)
    up = np.clip(np.floor((np.arange(n_hi) + 0.5) / s), 0, n_lo - 1).astype(np.intp)
    return down, up


def apply_noise(depth: np.ndarray, K: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator,
                rgb: np.ndarray | None = None) -> np.ndarray:
    """Turn a clean rendered depth map into a measurement of the sensor ``cfg`` describes, at the sensor's pitch.

    depth: (H, W) float metres, 0 = no measurement; K: (3, 3) pixels; rgb: (H, W, 3) uint8 or None. Returns
    (H, W) float32 metres, 0 = missing. When the image is finer than the depth sensor (:func:`native_pitch`
    s > 1: a depth image registered into a narrower colour camera), the clean depth is sampled at the
    sensor's own pixel centres (nearest), the noise of :func:`noise_at_pitch` is drawn there with K scaled by
    1/s, and each image pixel takes the measurement of the sensor pixel it lies in (nearest). Holes, edge
    bands, shadows and correlated errors then span s times more image pixels, as in registered real depth.
    With s = 1 this is :func:`noise_at_pitch` itself, draw for draw.
    """
    depth = np.asarray(depth)
    _check_inputs(depth, K)
    s = native_pitch(K, cfg) if cfg.enabled else 1.0
    if s == 1.0:
        return noise_at_pitch(depth, K, cfg, rng, rgb=rgb)
    h, w = depth.shape
    rows, up_r = _pitch_grid(h, s)
    cols, up_c = _pitch_grid(w, s)
    K = np.asarray(K, np.float64)
    K_lo = np.array([[K[0, 0] / s, K[0, 1] / s, (K[0, 2] + 0.5) / s - 0.5],
                     [0.0, K[1, 1] / s, (K[1, 2] + 0.5) / s - 0.5], [0.0, 0.0, 1.0]])
    rgb_lo = None
    if rgb is not None:
        rgb_lo = cv2.resize(np.ascontiguousarray(rgb), (len(cols), len(rows)), interpolation=cv2.INTER_AREA)
    lo = noise_at_pitch(np.ascontiguousarray(depth[np.ix_(rows, cols)]), K_lo, cfg, rng, rgb=rgb_lo)
    return np.ascontiguousarray(lo[np.ix_(up_r, up_c)])


def noise_at_pitch(depth: np.ndarray, K: np.ndarray, cfg: NoiseConfig, rng: np.random.Generator,
                   rgb: np.ndarray | None = None) -> np.ndarray:
    """Turn a clean rendered depth map into a Kinect-like measurement, one draw per image pixel.

    depth: (H, W) float metres, 0 (or non-finite) = no measurement; K: (3, 3) pixels (fx = K[0, 0]
    is used for disparity); rng: the frame's generator; rgb: (H, W, 3) uint8 colour of the same view, used
    by the dark and textureless dropouts (skipped without it). Returns (H, W) float32 metres, 0 = missing.
    With ``cfg.enabled`` False it returns an unchanged float32 copy and draws nothing. Effects whose
    parameter is 0 (the NoiseConfig defaults) draw nothing, so they leave the other effects' draws alone.

    Steps, all vectorised:
      1. incidence angles from the clean depth (:func:`normals_from_depth`, :func:`incidence_angle`;
         0 where a pixel has no normal, e.g. an isolated pixel);
      2. lateral noise: every pixel takes the value of the pixel nearest to its position jittered
         by N(0, lateral_px) in u and in v (i.e. a rounded-Gaussian shift, clamped at the border;
         nearest neighbour, so edges stay sharp but become ragged); angles move along;
      3. axial noise N(0, sigma_gauss) with sigma_gauss reduced from :func:`axial_sigma` by the
         quantisation variance (module docstring), so the total matches Nguyen et al.;
      4. disparity quantisation: d = fx b / z rounded to ``disparity_step_px``, z = fx b / d;
      5. holes: pixels on either side of a jump > ``edge_threshold`` between two measured
         4-neighbours (after step 2; a border to missing depth is not a jump) are lost with
         probability ``edge_dropout``; incidence angles > ``grazing_deg`` are lost; any pixel is lost
         with probability ``random_dropout``; measurements outside [min_range, max_range] are lost.
    Sensor-profile effects (off by default), in the order applied:
      a. ``shadow``: pixels the projector (stereo: the second camera) ``baseline`` to the right cannot see
         are lost (:func:`shadow_mask`, on the clean depth);
      b. ``multipath`` (ToF): concave regions read long (:func:`_multipath`), before step 2;
      c. ``edge_fatten_px`` (stereo): the nearer side of a discontinuity spreads over the farther one;
      d. ``scale_sigma``, ``offset_sigma``: one systematic z (1 + s) + o per frame, before the axial noise;
      e. ``correlated_sigma``: a spatially correlated axial error (:func:`correlated_field`, std
         ``correlated_sigma`` z^2) added with the white axial noise;
      f. ``flying``: a kept pixel at a discontinuity takes, with that probability, a depth drawn uniformly
         between the nearest and farthest depth of its 3 x 3 neighbourhood (mixed pixels);
      g. ``dark_dropout``, ``textureless_dropout``: holes on black surfaces and on flat 7 x 7 patches (rgb).
    """
    depth = np.asarray(depth)
    _check_inputs(depth, K)
    if not cfg.enabled:
        return depth.astype(np.float32, copy=True)
    h, w = depth.shape
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
    f32 = np.float32

    use_grazing = cfg.grazing_deg < 90.0
    theta = None
    if cfg.angle_term or use_grazing:
        theta = _incidence_from_depth(z, K)

    shadow = shadow_mask(z, K, cfg.baseline) if cfg.shadow else None
    if cfg.multipath > 0:
        z = _multipath(z, cfg.multipath, cfg.multipath_px)
    if cfg.edge_fatten_px > 0:
        z = _fatten(z, _discontinuities(z, cfg.edge_threshold), int(cfg.edge_fatten_px))

    if cfg.lateral_px > 0:
        pad, idx = _lateral_index(h, w, cfg.lateral_px, rng)
        z = _resample(z, pad, idx)
        if theta is not None:
            theta = _resample(theta, pad, idx)
        if shadow is not None:
            shadow = _resample(shadow, pad, idx)
    valid = z > 0
    if cfg.scale_sigma > 0 or cfg.offset_sigma > 0:
        s_, o_ = rng.normal(0.0, [max(cfg.scale_sigma, 1e-12), max(cfg.offset_sigma, 1e-12)])
        z = np.where(valid, z * f32(1.0 + s_) + f32(o_), f32(0.0)).astype(np.float32)

    fb = f32(float(K[0][0]) * cfg.baseline)  # pixels * metres
    step = f32(cfg.disparity_step_px)
    sigma = axial_sigma(z, theta if cfg.angle_term else f32(0.0), cfg)
    if step > 0:
        q = z * z * (step / fb)  # metres between neighbouring disparity levels at depth z
        sigma = np.sqrt(np.maximum(sigma * sigma - q * q / f32(12.0), f32(0.0)))
    noisy = z + rng.standard_normal((h, w), dtype=np.float32) * sigma
    if cfg.correlated_sigma > 0:
        noisy = noisy + correlated_field(h, w, cfg.correlated_px, rng) * (f32(cfg.correlated_sigma) * z * z)
    # the discontinuities after the lateral jitter: where flying pixels and edge dropout happen
    edge = _discontinuities(z, cfg.edge_threshold) if cfg.flying > 0 or cfg.edge_dropout > 0 else None
    if cfg.flying > 0:
        lo, hi = _minmax3(z)
        mixed = edge & (rng.random((h, w), dtype=np.float32) < f32(cfg.flying))
        a = rng.random((h, w), dtype=np.float32)
        noisy = np.where(mixed, lo + a * (hi - lo) + (noisy - z), noisy)

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if step > 0:
            d = np.rint(fb / noisy / step) * step
            noisy = np.where(d > 0, fb / d, f32(0.0))

    lost = ~valid | ~np.isfinite(noisy) | (noisy <= 0) | (noisy < cfg.min_range) | (noisy > cfg.max_range)
    if use_grazing:
        lost |= theta > f32(np.deg2rad(cfg.grazing_deg))
    if shadow is not None:
        lost |= shadow
    if rgb is not None and (cfg.dark_dropout > 0 or cfg.textureless_dropout > 0):
        lum = _luminance(rgb)
        p = np.zeros((h, w), np.float32)
        if cfg.dark_dropout > 0 and cfg.dark_level > 0:
            p = np.maximum(p, f32(cfg.dark_dropout) * np.clip(1 - lum / f32(cfg.dark_level), 0, 1))
        if cfg.textureless_dropout > 0:
            m = cv2.blur(lum, (7, 7))
            sd = np.sqrt(np.maximum(cv2.blur(lum * lum, (7, 7)) - m * m, 0))
            p = np.maximum(p, np.where(sd < f32(cfg.textureless_level), f32(cfg.textureless_dropout), f32(0)))
        lost |= rng.random((h, w), dtype=np.float32) < p
    p_rand, p_edge = cfg.random_dropout, cfg.edge_dropout
    if p_rand > 0 or p_edge > 0:
        # One uniform draw covers both independent dropouts: u < p_rand loses any pixel, and an edge
        # pixel is also lost for u in [p_rand, p_rand + (1 - p_rand) p_edge), i.e. overall with
        # probability 1 - (1 - p_rand)(1 - p_edge).
        u = rng.random((h, w), dtype=np.float32)
        lost |= u < f32(p_rand)
        if p_edge > 0:
            lost |= edge & (u < f32(p_rand + (1.0 - p_rand) * p_edge))
    noisy[lost] = 0.0
    return noisy.astype(np.float32, copy=False)
