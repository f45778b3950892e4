"""Compact, recolourable tables: a low-rank absorption basis stored with an error-bounded codec.

A table of the levels layout (:mod:`usdfiber.bake.storage`) keeps, per bin, ``p`` and the
mean path length at ``K = 11`` absorption levels (22 float16 values) so that any dye can be
applied later (:mod:`usdfiber.bake.absorption`). For one incoming direction, the recoloured
``p(. | omega_i; s)`` is a smooth curve in ``s``: ``F(s)`` is the Laplace transform of each
bin's path-length distribution, and such families are close to low-rank. This layout
(``usdfiber-bcsdf-absorption-basis`` version 1) stores, per incoming direction ``d``:

* ``R`` basis functions ``b_{d,j}`` over the band's bins (``basis``), and
* their coefficients ``c_{d,j}(s)`` at ``S`` sample absorptions ``s_m`` (``coef``):
  ``SAMPLES_PER_OCTAVE`` per doubling of ``s + c`` (``c`` half the first non-zero level) from
  0 to 16x the last level (:func:`sample_absorptions`), interpolated between samples by a
  natural cubic spline in the sample index; beyond the last sample the last sample's values
  (there only the shortest paths, surface reflection, are left).

Recoloured: ``p(s) = max(0, sum_j c_{d,j}(s) b_{d,j}) / norm`` with ``norm`` making it
integrate to 1 over the band; ``Lambda(s)`` is interpolated from the unchanged ``albedo`` and
``albedo_lbar`` arrays as before, so the albedo, and with it the furnace (Lambda = 1 at
s = 0), is kept exactly. Recolouring reads ``R`` values per bin for all colour channels
together instead of four per bin and channel (:func:`usdfiber.bake.recolour.recolour_basis`).

The basis is found per direction by a singular value decomposition of the reference
recoloured ``p`` at the sample absorptions, weighted so that its error is the relative L2
error over the sphere (``sqrt(domega) p``, each row scaled to unit norm). On disk the basis is compressed by blosc2's ZFP codec in fixed-accuracy mode (``ZFP_ACC``:
transform coding of 4^3 blocks of smooth float arrays, every value within an absolute
tolerance), one cframe per group of directions, each component scaled by its largest share of
p over the absorptions so that the tolerance spends bits where they matter; in memory it is
float16.

Error bound: the writer (:func:`compress_table`) recolours every direction at every sample
absorption and at the midpoints between them (in the sample index) from what it stores, as
the reader will, and compares with the uncompressed table recoloured there (the relative L2
error of ``p`` over the sphere). Where a group of directions exceeds ``bound`` it retries
with half the codec tolerance, then with more components; if nothing meets the bound it refuses
(:class:`CompressionError`). The worst error per direction is stored (``compression_error``)
and summarized in the header's ``compression`` entry with the codec, its bound, the rank
and the samples.

=====================  ============================  =====  ====================================
name                   shape                         dtype  meaning
=====================  ============================  =====  ====================================
``basis_codec``        (n_bytes,)                    u1     blosc2 cframes, one per group
``basis_groups``       (n_groups, 4)                 i8     first direction, directions, byte
                                                            offset, bytes
``basis_factor``       (n_ti, n_pi, R)               f4     basis = decoded x factor / sqrt(domega)
``coef``               (n_ti, n_pi, S, R)            f4     c_j(s_m) (basis scales folded in)
``absorptions``        (S,)                          f8     s_m, 1/um at the baked size
``compression_error``  (n_ti, n_pi)                  f4     worst relative L2 error of p over
                                                            the checked absorptions
``band_start``, ``albedo``, ``albedo_lbar``, ``levels``, ``width``, ``rel_error``, ``photons``:
as in the levels layout.
=====================  ============================  =====  ====================================

A file is read through the container's verified reader (every array's checksum: a truncated
file or a flipped byte is refused), then :func:`decode_basis` checks every cframe against the
header (codec, shape, dtype) and refuses a mismatch with one line naming the file.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

from usdfiber.bake.grid import Grid
from usdfiber.bake.storage import TableLayoutError

if TYPE_CHECKING:  # pragma: no cover
    from usdfiber.bake.table import BcsdfTable

__all__ = ["ARRAYS", "CODEC", "DEFAULT_BOUND", "LAYOUT", "LAYOUT_VERSION", "MAX_RANK", "SAMPLES_PER_OCTAVE",
           "CompressionError", "check_layout", "check_absorptions", "coefficients", "compress_table",
           "decode_basis", "reconstruct_p", "sample_absorptions"]

LAYOUT = "usdfiber-bcsdf-absorption-basis"
LAYOUT_VERSION = 1
#: The codec of ``basis_codec`` (recorded in the header; a file naming another is refused).
CODEC = "blosc2-zfp-acc"
#: Default bound on the relative L2 error of p per direction (the issue's 1 %).
DEFAULT_BOUND = 0.01
#: The smallest bound accepted: float16 p alone rounds by up to 5e-4 per value.
MIN_BOUND = 1e-4
#: Sample absorptions per doubling of s.
SAMPLES_PER_OCTAVE = 4
#: How often the codec tolerance of a group is halved before a higher rank is tried.
_TOLERANCE_HALVINGS = 10
#: The largest rank (basis functions per direction) tried.
MAX_RANK = 12
#: Absorptions recoloured per kernel launch while compressing.
_CHANNELS = 8
#: Bytes of reference p held at once while compressing (one group of directions).
_GROUP_BYTES = 1 << 29

ARRAYS: dict[str, str] = {
    "basis_codec": "blosc2 cframes of the basis, one per group of directions",
    "basis_groups": "per group: first direction, directions, byte offset, bytes",
    "basis_factor": "per (theta_i, phi_i, component): basis = decoded values x factor / sqrt(domega)",
    "coef": "coefficients of the basis at the sample absorptions, (theta_i, phi_i, sample, component)",
    "absorptions": "sample absorptions s_m, 1/um at the baked size",
    "compression_error": "worst relative L2 error of p per incoming direction over the checked absorptions",
    "band_start": "first theta_o row of the band per (theta_i, phi_i)",
    "albedo": "Lambda per (theta_i, phi_i, level)",
    "albedo_lbar": "-d log Lambda / d s per (theta_i, phi_i, level), um",
    "levels": "absorption levels s_k of the albedo, 1/um at the baked size",
    "width": "W(phi) at phi = 360 j / n_w deg, um at the baked size",
    "rel_error": "relative L2 error of p per incoming direction (sigma_a = 0), of the traced table",
    "photons": "photons traced per incoming direction",
}


class CompressionError(ValueError):
    """A table that cannot be compressed within the bound (the message says where and why)."""


# ---------------------------------------------------------------------------------------------
# Sample absorptions and the coefficient spline
# ---------------------------------------------------------------------------------------------

def sample_absorptions(levels: np.ndarray) -> np.ndarray:
    """``s_m = c (2^(m / q) - 1)``, m = 0, 1, ...: q = SAMPLES_PER_OCTAVE per doubling of
    ``s + c`` (c = half the first non-zero level) up to 16x the last level. The sample index
    is a smooth function of s (linear near 0, logarithmic beyond c), so the coefficient
    spline has no kink."""
    lv = np.asarray(levels, dtype=np.float64)
    c = lv[1] / 2 if len(lv) > 1 else 1.0 / 16
    hi = max(lv[-1] * 16, c * 2)
    n = int(math.ceil(SAMPLES_PER_OCTAVE * math.log2(1.0 + hi / c)))
    return c * (2.0 ** (np.arange(n + 1) / SAMPLES_PER_OCTAVE) - 1.0)


def _position(samples: np.ndarray, s: float) -> float:
    """Where ``s`` sits in the sample index (fractional; clamped to the last sample)."""
    c = float(samples[SAMPLES_PER_OCTAVE])
    return min(SAMPLES_PER_OCTAVE * math.log2(1.0 + max(s, 0.0) / c), float(len(samples) - 1))


def _absorption_at(samples: np.ndarray, u: float) -> float:
    """The inverse of :func:`_position`."""
    return float(samples[SAMPLES_PER_OCTAVE]) * (2.0 ** (u / SAMPLES_PER_OCTAVE) - 1.0)


def check_absorptions(samples: np.ndarray) -> np.ndarray:
    """The absorptions the writer checks: every sample and the midpoint between neighbours."""
    mids = [_absorption_at(samples, m + 0.5) for m in range(len(samples) - 1)]
    return np.concatenate([samples, mids])


def coefficients(samples: np.ndarray, coef: np.ndarray, sigmas) -> np.ndarray:
    """``c_j(s)`` for each absorption in ``sigmas``: (n_dir, C, R) float32 from the
    (n_dir, S, R) ``coef`` (natural cubic spline in the sample index)."""
    from scipy.interpolate import CubicSpline

    spline = CubicSpline(np.arange(len(samples)), coef, axis=1, bc_type="natural")
    u = np.array([_position(samples, float(s)) for s in sigmas])
    return spline(u).astype(np.float32)


def reconstruct_p(basis: np.ndarray, coef_c: np.ndarray, domega: np.ndarray) -> np.ndarray:
    """p per steradian, (n_dir, C, B * n_po) float32, from a (n_dir, R, B * n_po) basis, the
    (n_dir, C, R) coefficients and (n_dir, B * n_po) solid angles (numpy, the reference of
    :func:`usdfiber.bake.recolour.recolour_basis`)."""
    m = np.maximum(np.matmul(coef_c.astype(np.float32), basis.astype(np.float32)), 0.0)
    tot = np.einsum("dcb,db->dc", m, domega.astype(np.float32))
    inv = np.where(tot > 0, 1.0 / np.where(tot > 0, tot, 1.0), 0.0).astype(np.float32)
    return m * inv[..., None]


def _rel_l2(p: np.ndarray, ref: np.ndarray, dom: np.ndarray) -> np.ndarray:
    """Relative L2 over the sphere per (direction, absorption): p, ref (n, C, nb), dom (n, nb)."""
    num = np.einsum("dcb,db->dc", (p - ref) ** 2, dom)
    den = np.einsum("dcb,db->dc", ref ** 2, dom)
    return np.sqrt(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0))


# ---------------------------------------------------------------------------------------------
# The codec (blosc2 ZFP, fixed accuracy)
# ---------------------------------------------------------------------------------------------

def _encode(z: np.ndarray) -> bytes:
    """A (n, B, n_po) float32 array as one blosc2 cframe, ZFP with absolute tolerance 1
    (``codec_meta`` is the tolerance's power of ten as a signed byte)."""
    import blosc2

    n, B, n_po = z.shape
    cp = {"codec": blosc2.Codec.ZFP_ACC, "codec_meta": 0,
          "filters": [blosc2.Filter.NOFILTER], "splitmode": blosc2.SplitMode.NEVER_SPLIT}
    arr = blosc2.asarray(np.ascontiguousarray(z, dtype=np.float32), cparams=cp,
                         chunks=(min(n, 64), B, n_po), blocks=(min(n, 4), B, n_po))
    return bytes(arr.to_cframe())


def _decode(frame: bytes | memoryview, shape: tuple[int, ...], where: str) -> np.ndarray:
    import blosc2

    try:
        arr = blosc2.ndarray_from_cframe(bytes(frame))
        codec = arr.schunk.cparams.codec
        if codec != blosc2.Codec.ZFP_ACC:
            raise TableLayoutError(f"{where}: basis is stored with codec {codec.name}, the header says {CODEC}")
        if tuple(arr.shape) != tuple(shape) or arr.dtype != np.float32:
            raise TableLayoutError(f"{where}: a basis group has shape {tuple(arr.shape)} {arr.dtype}, "
                                   f"the header says {tuple(shape)} float32")
        return arr[:]
    except TableLayoutError:
        raise
    except Exception as exc:   # blosc2 raises RuntimeError/ValueError on damaged frames
        raise TableLayoutError(f"{where}: basis cannot be decoded ({type(exc).__name__}: {exc})") from None


def _unpack(z: np.ndarray, factor: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The float16 basis (n, R, nb) in p from decoded codec values: ``z * factor / w``."""
    return (z * factor[..., None] / w[:, None, :]).astype(np.float16)


def _weights(grid: Grid, band_start: np.ndarray, B: int) -> np.ndarray:
    """sqrt(domega) of every band bin, (n_dir, B * n_po) float32."""
    rows = band_start.reshape(-1, 1).astype(np.int64) + np.arange(B)
    return np.repeat(np.sqrt(grid.solid_angles()[rows]), grid.n_phi_o, axis=1).astype(np.float32)


def decode_basis(header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], where: str) -> np.ndarray:
    """The basis (n_ti, n_pi, R, B, n_po) float16 of a compressed table, every group checked
    against the header (codec, shape, dtype); TableLayoutError naming ``where`` otherwise."""
    comp = header.get("compression", {})
    if not isinstance(comp, dict) or comp.get("codec") != CODEC:
        raise TableLayoutError(f"{where}: codec {comp.get('codec') if isinstance(comp, dict) else comp!r} "
                               f"is not {CODEC}")
    try:
        R, B = int(comp["rank"]), int(comp["band"])
    except (KeyError, TypeError, ValueError):
        raise TableLayoutError(f"{where}: the header's compression entry lacks rank or band") from None
    g = _grid(header, where)
    n_dir, n_po = g.n_theta_i * g.n_phi_i, g.n_phi_o
    blob = arrays["basis_codec"]
    factor = arrays["basis_factor"].reshape(n_dir, R)
    w = _weights(g, arrays["band_start"], B)
    out = np.empty((n_dir, R, B * n_po), dtype=np.float16)
    seen = 0
    for first, count, offset, nbytes in arrays["basis_groups"].tolist():
        if first != seen or count <= 0 or offset < 0 or offset + nbytes > blob.size:
            raise TableLayoutError(f"{where}: basis groups do not tile the directions or the codec bytes")
        z = _decode(memoryview(blob)[offset:offset + nbytes], (count * R, B, n_po), where)
        sl = slice(first, first + count)
        out[sl] = _unpack(z.reshape(count, R, B * n_po), factor[sl], w[sl])
        seen += count
    if seen != n_dir:
        raise TableLayoutError(f"{where}: basis groups cover {seen} of {n_dir} directions")
    return out.reshape(g.n_theta_i, g.n_phi_i, R, B, n_po)


def _grid(header: Mapping[str, Any], where: str) -> Grid:
    try:
        return Grid.from_header(header["resolution"])
    except (KeyError, TypeError, ValueError) as exc:
        raise TableLayoutError(f"{where}: bad resolution entry in the header: {exc}") from None


def check_layout(header: Mapping[str, Any], arrays: Mapping[str, np.ndarray], where: str) -> Grid:
    """The grid of a compressed table, after checking its arrays against this layout."""
    missing = [n for n in ARRAYS if n not in arrays]
    if missing:
        raise TableLayoutError(f"{where}: missing array(s) {', '.join(missing)}")
    lay = header.get("layout", {})
    if not isinstance(lay, dict) or lay.get("version") != LAYOUT_VERSION:
        raise TableLayoutError(f"{where}: unsupported array layout {lay!r} "
                               f"(this usdfiber reads {LAYOUT} version {LAYOUT_VERSION})")
    g = _grid(header, where)
    comp = header.get("compression", {})
    try:
        R, B = int(comp["rank"]), int(comp["band"])
    except (KeyError, TypeError, ValueError):
        raise TableLayoutError(f"{where}: the header's compression entry lacks rank or band") from None
    dirs = (g.n_theta_i, g.n_phi_i)
    S = len(arrays["absorptions"])
    K = len(arrays["levels"])
    want = {"coef": dirs + (S, R), "basis_factor": dirs + (R,), "compression_error": dirs, "band_start": dirs,
            "albedo": dirs + (K,), "albedo_lbar": dirs + (K,), "rel_error": dirs, "photons": dirs}
    for name, shape in want.items():
        if arrays[name].shape != shape:
            raise TableLayoutError(f"{where}: array {name} has shape {arrays[name].shape}, expected {shape}")
    if arrays["basis_groups"].ndim != 2 or arrays["basis_groups"].shape[1] != 4:
        raise TableLayoutError(f"{where}: array basis_groups has shape {arrays['basis_groups'].shape}")
    if "basis" in arrays and arrays["basis"].shape != dirs + (R, B, g.n_phi_o):
        raise TableLayoutError(f"{where}: array basis has shape {arrays['basis'].shape}")
    bs = arrays["band_start"]
    if B <= 0 or B > g.n_theta_o or np.any(bs < 0) or np.any(bs + B > g.n_theta_o):
        raise TableLayoutError(f"{where}: band out of range")
    if not np.array_equal(arrays["absorptions"], sample_absorptions(arrays["levels"])):
        raise TableLayoutError(f"{where}: sample absorptions differ from this usdfiber's "
                               f"({SAMPLES_PER_OCTAVE} per octave)")
    return g


# ---------------------------------------------------------------------------------------------
# The writer
# ---------------------------------------------------------------------------------------------

def _basis_of(x: np.ndarray, w: np.ndarray, rank: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per direction, the leading ``rank`` right singular vectors ``v`` (n, R, nb) of the rows
    ``x * w`` (x: (n, S, nb) p at the samples; each row scaled to unit norm for the
    decomposition), the coefficients (n, S, R) with ``coef @ v ~ x * w``, and each
    component's importance (n, R): its largest share of a row's norm."""
    xw = x * w[:, None, :]
    nrm = np.linalg.norm(xw, axis=2, keepdims=True)
    xn = xw / np.where(nrm > 0, nrm, 1.0)
    gram = np.matmul(xn, np.swapaxes(xn, 1, 2)).astype(np.float64)
    from threadpoolctl import threadpool_limits     # (a dependency of blosc2)

    # Thousands of tiny eigenproblems: BLAS threads only wait on each other (measured 17x
    # slower with 2 threads on a busy 2-core machine).
    with threadpool_limits(1):
        lam, u = np.linalg.eigh(gram)                   # ascending
    lam, u = lam[:, ::-1][:, :rank], u[:, :, ::-1][:, :, :rank]
    sq = np.sqrt(np.maximum(lam, 0.0))
    v = np.matmul(np.swapaxes(u, 1, 2).astype(np.float32), xn)            # (n, R, nb) = sq * V
    # Components below float32 resolution of the leading one carry nothing but rounding.
    v = v / np.where(sq > 1e-5 * sq[:, :1], sq, np.inf)[..., None].astype(np.float32)
    coef = np.matmul(xw, np.swapaxes(v, 1, 2))
    share = np.abs(coef) / np.where(nrm > 0, nrm, np.inf)
    return v, coef.astype(np.float32), share.max(axis=1).astype(np.float32)


def compress_table(table: "BcsdfTable", bound: float = DEFAULT_BOUND, *, rank: int | None = None,
                   progress: Callable[[int, int], None] | None = None) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """``(header, arrays)`` of ``table`` (levels layout) in the absorption-basis layout,
    every direction within ``bound`` relative L2 error of p at every checked absorption.

    ``rank``: the number of basis functions (default: the smallest that meets half the bound
    on a probe of directions). Each group of directions is encoded with the largest codec
    tolerance (halved from ``8 bound / sqrt(bins)`` until it fits) that keeps the bound.
    Raises CompressionError when a direction cannot meet the bound.
    """
    import blosc2

    if not (MIN_BOUND <= bound < 1):
        raise CompressionError(f"bound must be in [{MIN_BOUND:g}, 1), got {bound}")
    if table.compressed:
        raise CompressionError(f"{table.path or 'table'}: is already compressed")
    g = table.grid
    n_ti, n_pi = g.n_theta_i, g.n_phi_i
    n_dir, B, n_po = n_ti * n_pi, table.n_band, g.n_phi_o
    nb = B * n_po
    samples = sample_absorptions(table.levels)
    checks = check_absorptions(samples)
    S = len(samples)
    w_all = _weights(g, table.band_start, B)
    dom_all = w_all ** 2

    def reference(idx: np.ndarray) -> np.ndarray:     # (n, C, nb) float32 at every check
        out = np.empty((len(idx), len(checks), nb), np.float32)
        for c0 in range(0, len(checks), _CHANNELS):   # a few channels per kernel launch
            cs = checks[c0:c0 + _CHANNELS]
            out[:, c0:c0 + len(cs)] = np.moveaxis(table.p_directions(cs, idx).reshape(len(idx), nb, len(cs)), 2, 1)
        return out

    def errors(basis: np.ndarray, coef: np.ndarray, ref: np.ndarray, dom: np.ndarray) -> np.ndarray:
        c = coefficients(samples, coef, checks)
        return _rel_l2(reconstruct_p(basis, c, dom), ref, dom).max(axis=1)

    if rank is None:
        probe = np.unique(np.linspace(0, n_dir - 1, min(n_dir, 64)).round().astype(np.int64))
        ref = reference(probe)
        v, coef, _ = _basis_of(ref[:, :S], w_all[probe], MAX_RANK)
        basis = v / w_all[probe][:, None, :]
        rank = MAX_RANK
        for r in range(1, MAX_RANK + 1):
            if errors(basis[:, :r], coef[:, :, :r], ref, dom_all[probe]).max() <= 0.5 * bound:
                rank = r
                break
    rank = min(int(rank), S)
    per = max(1, min(n_dir, _GROUP_BYTES // (4 * len(checks) * nb)))
    frames: list[bytes] = []
    groups: list[list[int]] = []
    coef_all = np.empty((n_dir, S, rank), np.float32)
    factor_all = np.empty((n_dir, rank), np.float32)
    err_all = np.empty(n_dir, np.float32)
    tolerances = []
    offset = 0
    for d0 in range(0, n_dir, per):
        idx = np.arange(d0, min(n_dir, d0 + per))
        ref = reference(idx)
        w, dom = w_all[idx], dom_all[idx]
        v, coef, share = _basis_of(ref[:, :S], w, rank)
        # Each component is stored as v * share / tol, and the codec keeps every value within
        # 1 of it: a component's absolute error is at most tol over its share of a row.
        mx = np.abs(v / w[:, None, :]).max(axis=2)
        mx = np.where(mx > 0, mx, 1.0)
        tol = 8 * bound / math.sqrt(nb)
        for _ in range(_TOLERANCE_HALVINGS):
            z = v * (share / tol)[..., None]
            frame = _encode(z.reshape(-1, B, n_po))
            factor = np.where(share > 0, tol / (np.where(share > 0, share, 1.0) * mx), 0.0).astype(np.float32)
            zd = _decode(frame, (len(idx) * rank, B, n_po), "compressing").reshape(len(idx), rank, nb)
            basis = _unpack(zd, factor, w)
            err = errors(basis, coef * mx[:, None, :], ref, dom)
            if err.max() <= bound:
                break
            tol /= 2
        if err.max() > bound:
            worst = int(idx[np.argmax(err)])
            if rank < min(MAX_RANK, S):   # more components for the whole table
                return compress_table(table, bound, rank=rank + 1, progress=progress)
            ti, pi = divmod(worst, n_pi)
            raise CompressionError(f"{table.path or 'table'}: incoming direction ({ti}, {pi}) keeps a "
                                   f"compression error of {err.max():.3%} > {bound:.3%} at rank {rank}")
        coef_all[idx] = coef * mx[:, None, :]
        factor_all[idx] = factor
        err_all[idx] = err
        tolerances.append(tol)
        frames.append(frame)
        groups.append([int(idx[0]), len(idx), offset, len(frame)])
        offset += len(frame)
        if progress is not None:
            progress(int(idx[-1]) + 1, n_dir)
    a = table.arrays
    arrays = {
        "basis_codec": np.frombuffer(b"".join(frames), dtype=np.uint8),
        "basis_groups": np.asarray(groups, dtype=np.int64).reshape(-1, 4),
        "basis_factor": factor_all.reshape(n_ti, n_pi, rank),
        "coef": coef_all.reshape(n_ti, n_pi, S, rank),
        "absorptions": samples,
        "compression_error": err_all.reshape(n_ti, n_pi),
        **{k: a[k] for k in ("band_start", "albedo", "albedo_lbar", "levels", "width", "rel_error", "photons")},
    }
    header = {k: v for k, v in table.header.items() if k not in ("arrays", "checksums", "format", "version")}
    header["layout"] = {"name": LAYOUT, "version": LAYOUT_VERSION, "arrays": dict(ARRAYS)}
    header["compression"] = {
        "codec": CODEC, "blosc2": blosc2.__version__, "bound": float(bound), "rank": int(rank), "band": int(B),
        "samples_per_octave": SAMPLES_PER_OCTAVE, "checked_absorptions": len(checks),
        "error_max": float(err_all.max()), "error_rms": float(np.sqrt(np.mean(err_all.astype(np.float64) ** 2))),
        "tolerance_range": [float(min(tolerances)), float(max(tolerances))],
        "source_layout": table.header.get("layout", {}).get("name"),
    }
    return header, arrays
