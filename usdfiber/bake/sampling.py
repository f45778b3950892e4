"""Scrambled quasi-random numbers for the first dimensions of a photon, and independent streams.

A photon's first random numbers are the beam offset h and the first boundary event (the
microfacet normal and the Fresnel choice; for a smooth boundary the Fresnel choice alone).
For a smooth profile they decide most of its fate; once a rough boundary's microsurface walk
randomises the path they decide little (the measured gain: bench/REPORT.md, section 7).
:func:`sobol_points` gives those dimensions from the first four
dimensions of the Sobol sequence (Joe & Kuo direction numbers), Owen-scrambled with a hash
(Burley 2020, "Practical Hash-based Owen Scrambling"): every point is uniform on the unit
hypercube, so an estimator fed by them is unbiased, while the N points of one batch are
stratified in every elementary interval, which lowers the variance where the far field is a
smooth function of those dimensions.

The scramble is seeded per stream (a batch of an incoming direction), so estimates of
different directions and of different batches are independent (the spread between batches
stays a valid error estimate). :func:`stream_seed` derives such per-direction streams.
"""
from __future__ import annotations

import numpy as np

__all__ = ["QMC_DIMENSIONS", "box_power", "cos2_latitude", "owen_scramble", "scramble_seeds", "sobol_points", "sobol_unscrambled",
           "stream_seed", "to_unit_float"]

#: Dimensions drawn from the sequence: h, then the first boundary event's three numbers.
QMC_DIMENSIONS = 4

_BITS = 32
_M32 = np.uint64(0xFFFFFFFF)


def _direction_numbers() -> np.ndarray:
    """(4, 32) uint32 direction numbers v[d, k] for index bit k (Joe & Kuo 2008, dims 1-4)."""
    # Dimension 1 is the van der Corput sequence; dims 2-4 from the primitive polynomials
    # (degree s, coefficients a, initial m): (1, 0, [1]), (2, 1, [1, 3]), (3, 1, [1, 3, 1]).
    polys = [(1, 0, [1]), (2, 1, [1, 3]), (3, 1, [1, 3, 1])]
    v = np.zeros((QMC_DIMENSIONS, _BITS), dtype=np.uint64)
    v[0] = [1 << (31 - k) for k in range(_BITS)]
    for d, (s, a, m) in enumerate(polys, start=1):
        for k in range(_BITS):
            if k < s:
                v[d, k] = m[k] << (31 - k)
            else:
                x = v[d, k - s] ^ (v[d, k - s] >> np.uint64(s))
                for j in range(1, s):
                    if (a >> (s - 1 - j)) & 1:
                        x ^= v[d, k - j]
                v[d, k] = x
    return (v & _M32).astype(np.uint32)


_V = _direction_numbers()


def _const(like, value: int):
    """An unsigned 32-bit constant in the array module of ``like`` (numpy or Dr.Jit)."""
    return np.uint32(value) if isinstance(like, np.ndarray) else value


def sobol_unscrambled(index):
    """The 4 Sobol coordinates (32-bit fixed point) of ``index``: a list of 4 uint32 arrays.

    ``index`` is a numpy uint32 array or a Dr.Jit ``UInt32`` (the same code runs in the
    tracer's kernel); each coordinate XORs the direction numbers of the index's set bits.
    """
    one = _const(index, 1)
    full = _const(index, 0xFFFFFFFF)
    out = [index & _const(index, 0) for _ in range(QMC_DIMENSIONS)]
    for k in range(_BITS):
        mask = ((index >> _const(index, k)) & one) * full
        for d in range(QMC_DIMENSIONS):
            out[d] = out[d] ^ (mask & _const(index, int(_V[d, k])))
    return out


def _reverse_bits(x):
    c = lambda v: _const(x, v)  # noqa: E731
    x = ((x >> c(1)) & c(0x55555555)) | ((x & c(0x55555555)) << c(1))
    x = ((x >> c(2)) & c(0x33333333)) | ((x & c(0x33333333)) << c(2))
    x = ((x >> c(4)) & c(0x0F0F0F0F)) | ((x & c(0x0F0F0F0F)) << c(4))
    x = ((x >> c(8)) & c(0x00FF00FF)) | ((x & c(0x00FF00FF)) << c(8))
    return (x >> c(16)) | (x << c(16))


def owen_scramble(x, seed):
    """Nested uniform (Owen) scramble of 32-bit fixed-point values: a bit's flip depends on the
    bits above it only (Laine-Karras hash on the reversed bits, Burley 2020). numpy or Dr.Jit."""
    c = lambda v: _const(x, v)  # noqa: E731
    with np.errstate(over="ignore"):
        y = _reverse_bits(x)
        y = y + seed
        y = y ^ (y * c(0x6C50B47C))
        y = y ^ (y * c(0xB82F1E52))
        y = y ^ (y * c(0xC7AFE638))
        y = y ^ (y * c(0x8D22F6E6))
    return _reverse_bits(y)


def scramble_seeds(stream: np.ndarray) -> np.ndarray:
    """(n, 4) uint32 Owen-scramble seeds, one per dimension, of the streams ``stream`` (uint64)."""
    st = np.asarray(stream, dtype=np.uint64).reshape(-1)
    return np.stack([_hash32(st, d) for d in range(QMC_DIMENSIONS)], axis=-1)


def _hash32(key: np.ndarray, salt: int) -> np.ndarray:
    """32-bit seeds from 64-bit keys (splitmix64 finaliser)."""
    with np.errstate(over="ignore"):
        z = np.asarray(key, dtype=np.uint64) + np.uint64((0x9E3779B97F4A7C15 * (salt + 1)) & 0xFFFFFFFFFFFFFFFF)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z & _M32).astype(np.uint32)


def sobol_points(index: np.ndarray, stream: np.ndarray) -> np.ndarray:
    """(n, 4) float32 points in [0, 1): Sobol point ``index`` of the scrambled stream ``stream``.

    ``index`` (< 2^32): the photon's number in its stream; ``stream`` (uint64, one or one per
    point): the stream's key (one per direction and batch). Each dimension has its own
    scramble seed. The numpy twin of what the tracer computes in its kernel.
    """
    idx = np.asarray(index, dtype=np.uint64).astype(np.uint32).reshape(-1)
    seeds = scramble_seeds(stream)
    n = max(len(idx), len(seeds))
    idx, seeds = np.broadcast_to(idx, (n,)), np.broadcast_to(seeds, (n, QMC_DIMENSIONS))
    x = sobol_unscrambled(idx)
    out = np.empty((n, QMC_DIMENSIONS), dtype=np.float32)
    for d in range(QMC_DIMENSIONS):
        out[:, d] = to_unit_float(owen_scramble(x[d], seeds[:, d]))
    return out


def to_unit_float(y):
    """[0, 1) float32 from 32-bit fixed point: the top 24 bits (exact in float32, below 1)."""
    if isinstance(y, np.ndarray):
        return (y >> np.uint32(8)).astype(np.float32) * np.float32(2.0 ** -24)
    import drjit as dr

    return dr.float32_array_t(type(y))(y >> 8) * (2.0 ** -24)


#: Newton steps of :func:`cos2_latitude` (each bracketed: a rejected step bisects instead).
_LATITUDE_STEPS = 12


def cos2_latitude(a, b, u):
    """Latitudes in [a, b] (radians, within [-pi/2, pi/2]) with density proportional to
    cos^2(theta), from uniform numbers ``u`` in [0, 1): numpy or Dr.Jit float64 arrays.

    A box-filtered incoming bin (``BakeSettings(incoming="box")``) draws each photon's light
    direction uniformly in the power the fiber intercepts: solid angle cos(theta) dtheta dphi
    times the projected width W(phi) cos(theta), whose W is left to the beam (photons spread
    over a fixed launch width meet the fiber in proportion to W). So every photon that meets
    the fiber carries the same power. The inverse of the CDF, g(theta) = theta +
    sin(theta) cos(theta) (twice the integral of cos^2), is found by Newton's method kept
    inside the bracket that holds the root (a step that would leave it bisects), from the
    point of the uniform guess; 12 steps put g within 1e-11 of its target (relative to the
    bin's) in every 2 degree bin, including the last one at the pole, where g is cubic.
    """
    if isinstance(u, np.ndarray) or np.isscalar(u):
        sin, cos, select = np.sin, np.cos, np.where
        a, b, u = (np.asarray(x, dtype=np.float64) for x in (a, b, u))
    else:
        import drjit as dr

        sin, cos, select = dr.sin, dr.cos, dr.select
    target = (a + sin(a) * cos(a)) * (1.0 - u) + (b + sin(b) * cos(b)) * u
    lo, hi = a + 0.0 * u, b + 0.0 * u
    t = a + (b - a) * u
    for _ in range(_LATITUDE_STEPS):
        s, c = sin(t), cos(t)
        f = t + s * c - target
        below = f < 0.0
        lo, hi = select(below, t, lo), select(below, hi, t)
        slope = 2.0 * c * c
        step = t - f / select(slope > 0.0, slope, 1.0)
        inside = (slope > 0.0) & (step >= lo) & (step <= hi)
        t = select(inside, step, 0.5 * (lo + hi))
    return t


def box_power(theta_lo: float, theta_hi: float, widths: np.ndarray) -> float:
    """Power per unit irradiance and solid angle that a box-filtered incoming bin sends onto
    the fiber: (1/|I|) integral over I of W(phi) cos(theta), I = [theta_lo, theta_hi] x
    (the phi range of ``widths``), from ``widths`` = W(phi) at equally spaced azimuths over
    the bin (its ends included; one value for a single azimuth): the trapezoid mean of W
    times the mean of cos(theta) in solid angle, (int cos^2) / (int cos)."""
    w = np.asarray(widths, dtype=np.float64)
    mean_w = float(w[0]) if w.size == 1 else float(np.mean(0.5 * (w[1:] + w[:-1])))
    c2 = 0.5 * ((theta_hi - theta_lo) + 0.5 * (np.sin(2.0 * theta_hi) - np.sin(2.0 * theta_lo)))
    c1 = float(np.sin(theta_hi) - np.sin(theta_lo))
    return mean_w * float(c2) / c1


def stream_seed(seed: int, batch: int, ti: int, pi: int) -> int:
    """A tracer seed distinct per (seed, batch, incoming node): independent directions.

    The plain estimator shares one stream between the directions of a batch (common random
    numbers); estimators that combine directions (reciprocity) or rely on per-stream
    stratification need independent ones.
    """
    key = np.array([(int(seed) & 0xFFFFFFFF) << 32 | (int(batch) & 0xFFFFFFFF)], dtype=np.uint64)
    a = int(_hash32(key, 11)[0])
    b = int(_hash32(np.array([(int(ti) & 0xFFFF) << 16 | (int(pi) & 0xFFFF)], dtype=np.uint64) ^ key, 13)[0])
    return (a << 32) | b
