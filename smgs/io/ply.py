"""The Gaussian-splatting PLY of the original 3DGS code (``GaussianModel.save_ply``), read and written
with ``plyfile`` (what that code uses).

One element ``vertex``, one float32 property per value, binary little-endian, in this order::

    x y z  nx ny nz  f_dc_0..2  f_rest_0..M-1  opacity  scale_0..2  rot_0..3  [extras]

* ``f_dc_c`` = SH coefficient 0 of colour channel c; ``f_rest_{c·(K−1)+j}`` = coefficient j+1 of
  channel c (channel-major: 3DGS flattens ``features_rest.transpose(1, 2)``), K = (degree+1)², so
  M = 3·(K−1) ∈ {0, 9, 24, 45} gives the SH degree 0..3.
* ``opacity`` is the logit (opacity = sigmoid), ``scale_i`` the log (scale = exp), ``rot_0..3``
  the quaternion w, x, y, z as stored (the renderer normalises it). ``nx ny nz`` are zeros in
  3DGS files; they are optional on reading and ignored.
* Softmax-GS extras (standard viewers ignore unknown properties): ``gef_alpha`` (GEF sharpness
  α), ``softmax_beta`` (β), ``softmax_gamma`` (γ), each the raw pre-activation value. Their
  activations are header comments written by smgs (``comment smgs activation.gef_alpha exp``):
  α = act(raw), β = act(raw), γ = act(raw) / extent in 1/world-length, act ∈ {exp, softplus},
  extent from ``comment smgs extent <value>`` (γ is stored relative to the scene extent). A file
  without those comments is read with exp and the scene's extent (smgs's defaults).

* Other tools' properties: normals and ``red green blue`` (a point cloud's preview colours) are
  read past; Mip-Splatting's ``filter_3D`` is folded into scale and opacity as its fused export
  does (``fold_filter_3d``); any other property (a 4D model's time and motion) is refused by name.

``comment smgs <key> <value>`` lines also carry the render settings of the model (mode, k_max,
eq15, t_min, clamp_colors) so a model renders the same after a round trip.

Reading accepts ASCII and big-endian files too (plyfile reads them); every other problem is a
``PlyFormatError`` naming the file, what is wrong and what was expected. Writing goes to a
temporary file in the same folder that replaces the target only when complete.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import plyfile
from numpy.lib.recfunctions import structured_to_unstructured

from smgs.atomic import atomic_file
from smgs.raster.constants import MAX_SH_DEGREE

EXTRAS: tuple[str, ...] = ("gef_alpha", "softmax_beta", "softmax_gamma")
"""The Softmax-GS extra properties (raw, pre-activation values)."""

ACTIVATIONS = ("exp", "softplus")

FILTER_3D = "filter_3D"
"""Mip-Splatting's per-Gaussian 3D smoothing filter (a world length), folded in on reading."""
FILTER_3D_NOTE = ("folded into scale and opacity as Mip-Splatting's save_fused_ply does; its 2D Mip filter is not "
                  "reproduced (rendered with 3DGS's screen-space dilation)")

NOT_RENDERED = frozenset({"nx", "ny", "nz", "red", "green", "blue"})
"""Properties of other tools that do not change how a model renders: normals (zeros in 3DGS files)
and a point cloud's 8-bit preview colours. Any other unknown property is refused (``read_ply``)."""
_COMMENT = "smgs"


class PlyFormatError(ValueError):
    """A PLY file that is not a readable 3DGS Gaussian-splatting PLY."""

    def __init__(self, path: Path | str, problem: str, expected: str = "") -> None:
        self.path, self.problem = Path(path), problem
        super().__init__(f"{path}: {problem}" + (f"; expected {expected}" if expected else ""))


@dataclass
class PlySplats:
    """The Gaussians of one PLY file as stored (no activation applied), float32 numpy arrays.

    means [N,3]; sh [N,K,3] with K = (degree+1)² (index 0 the DC term, as 3DGS ``features_dc``
    then ``features_rest``); opacities [N] (logits); scales [N,3] (logs); quats [N,4] (wxyz);
    extras: name -> [N] raw values (a subset of ``EXTRAS``); meta: the ``comment smgs`` key/values.
    """

    means: np.ndarray
    sh: np.ndarray
    opacities: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return math.isqrt(self.sh.shape[1]) - 1

    @property
    def mode(self) -> str:
        """The render mode the extras call for: none → 3dgs, α → gef_only, β and γ → softmax_only,
        all three → softmax_gs."""
        return mode_for_extras(set(self.extras))

    def check(self, where: Path | str = "<splats>") -> None:
        n = len(self)
        k = self.sh.shape[1] if self.sh.ndim == 3 else -1
        shapes = {"means": (self.means, (n, 3)), "sh": (self.sh, (n, k, 3)), "opacities": (self.opacities, (n,)),
                  "scales": (self.scales, (n, 3)), "quats": (self.quats, (n, 4))}
        shapes |= {name: (v, (n,)) for name, v in self.extras.items()}
        for name, (arr, shape) in shapes.items():
            if arr.shape != shape:
                raise PlyFormatError(where, f"{name} has shape {arr.shape}", f"{list(shape)}")
        if k < 1 or math.isqrt(k) ** 2 != k or math.isqrt(k) - 1 > MAX_SH_DEGREE:
            raise PlyFormatError(where, f"{k} SH coefficients per channel", "(degree+1)² for degree 0..3")
        mode_for_extras(set(self.extras), where)


def mode_for_extras(extras: set[str], where: Path | str = "<splats>") -> str:
    unknown = extras - set(EXTRAS)
    if unknown:
        raise PlyFormatError(where, f"unknown extra(s) {sorted(unknown)}", f"a subset of {list(EXTRAS)}")
    soft = {"softmax_beta", "softmax_gamma"} & extras
    if len(soft) == 1:
        raise PlyFormatError(where, f"{soft.pop()} without its partner",
                             "softmax_beta and softmax_gamma together (or neither)")
    return {(False, False): "3dgs", (True, False): "gef_only", (False, True): "softmax_only",
            (True, True): "softmax_gs"}[("gef_alpha" in extras, bool(soft))]


def property_names(sh_degree: int, extras: tuple[str, ...] | list[str] = ()) -> list[str]:
    """The vertex properties of a file of this degree, in the original code's order."""
    rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(rest)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                      "rot_0", "rot_1", "rot_2", "rot_3"]
            + [e for e in EXTRAS if e in extras])


# ---- writing -----------------------------------------------------------------------------------

def write_ply(path: Path | str, splats: PlySplats) -> Path:
    """Write ``splats`` as a binary little-endian 3DGS PLY (normals zero, as 3DGS writes them).
    The file appears complete or not at all: a temporary file in the same folder is fsynced and
    renamed over ``path``; on any error it is removed and ``path`` is left as it was."""
    path = Path(path)
    splats.check(path)
    _check_finite(path, {name: (int(np.isnan(a).sum()), int(np.isinf(a).sum()))
                         for name, a in _columns(splats).items() if not np.isfinite(a).all()},
                  "finite values (nothing was written)")
    n, k = len(splats), splats.sh.shape[1]
    extras = [e for e in EXTRAS if e in splats.extras]
    cols = [splats.means, np.zeros((n, 3), np.float32), splats.sh[:, 0, :],
            # channel-major f_rest: [N, K-1, 3] -> [N, 3, K-1] -> flat
            np.ascontiguousarray(splats.sh[:, 1:, :].transpose(0, 2, 1)).reshape(n, 3 * (k - 1)),
            splats.opacities[:, None], splats.scales, splats.quats] + [splats.extras[e][:, None] for e in extras]
    table = np.ascontiguousarray(np.concatenate([np.asarray(c, dtype=np.float32) for c in cols], axis=1), dtype="<f4")
    names = property_names(splats.sh_degree, extras)
    assert table.shape[1] == len(names)
    data = table.view(np.dtype([(name, "<f4") for name in names])).reshape(n)
    comments = [f"{_COMMENT} {key} {value}" for key, value in splats.meta.items()]
    ply = plyfile.PlyData([plyfile.PlyElement.describe(data, "vertex")], text=False, byte_order="<",
                          comments=comments)
    with atomic_file(path) as f:
        ply.write(f)
    return path


# ---- reading -----------------------------------------------------------------------------------

def read_ply(path: Path | str) -> PlySplats:
    """Read a 3DGS PLY: the SH degree from the number of ``f_rest_*`` properties, normals optional,
    Softmax-GS extras recognised, Mip-Splatting's ``filter_3D`` folded in (``fold_filter_3d``),
    preview colours read past (listed in ``meta["ignored"]``), any other property refused.
    Raises ``PlyFormatError`` (file, problem, expectation) for anything else."""
    path = Path(path)
    if not path.is_file():
        raise PlyFormatError(path, "no such file", "a .ply file written by 3DGS, gsplat, nerfstudio or smgs")
    if path.stat().st_size == 0:
        raise PlyFormatError(path, "empty file (0 bytes)", "a PLY header starting with 'ply'")
    header = _header(path)
    _check_sizes(path, header)   # before plyfile allocates what the header claims
    try:
        ply = plyfile.PlyData.read(str(path))   # memory-mapped: its non-mmap path reads row by row
    except (plyfile.PlyHeaderParseError, UnicodeDecodeError) as e:
        raise PlyFormatError(path, f"not a readable PLY header ({type(e).__name__}: {e})",
                             "'ply', 'format binary_little_endian 1.0', 'element vertex N', properties, "
                             "'end_header' as ASCII text") from e
    except plyfile.PlyElementParseError as e:
        raise PlyFormatError(path, f"truncated or corrupt data ({e}){_size_note(header)}",
                             "as many rows as the header's 'element vertex N' declares") from e
    if "vertex" not in ply:
        raise PlyFormatError(path, f"no 'vertex' element (elements: {[el.name for el in ply.elements]})",
                             "one element 'vertex' holding the Gaussians")
    vertex = ply["vertex"]
    n = vertex.count   # 0 is a model of nothing (a collapsed run's export): read as written
    names = [p.name for p in vertex.properties]
    for p in vertex.properties:
        if isinstance(p, plyfile.PlyListProperty):
            raise PlyFormatError(path, f"property {p.name!r} is a list", "scalar properties only")
    meta = _meta(ply.comments)
    fmt = "ascii" if ply.text else {"<": "binary_little_endian", ">": "binary_big_endian"}.get(
        ply.byte_order, "binary_little_endian" if np.little_endian else "binary_big_endian")
    meta["format"] = fmt
    present = set(names)
    base = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
            "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [q for q in base if q not in present]
    if missing:
        packed = " (a compressed PLY: save it uncompressed from SuperSplat first)" if "packed_position" in present else ""
        raise PlyFormatError(path, f"missing properties {missing} (found {_short(names)}){packed}",
                             "the 3DGS layout x y z [nx ny nz] f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3")
    rest_idx = sorted(_rest_index(path, q) for q in names if q.startswith("f_rest"))
    m = len(rest_idx)
    if rest_idx != list(range(m)):
        gaps = sorted(set(range(max(rest_idx, default=-1) + 1)) - set(rest_idx))
        raise PlyFormatError(path, f"f_rest_* indices are not 0..{m - 1} (missing {gaps[:10]})",
                             "f_rest_0 .. f_rest_{M-1} without gaps")
    degree = _degree(path, m)
    k = (degree + 1) ** 2
    _check_rendered(path, names, set(base) | {f"f_rest_{i}" for i in range(m)} | set(EXTRAS) | {FILTER_3D})
    # one float32 table [N, P] in one pass (any scalar type, either byte order); columns are
    # gathered by index, row by row (a strided pass per column would cost one pass per property)
    table = structured_to_unstructured(np.asarray(vertex.data), dtype=np.float32)
    where = {q: i for i, q in enumerate(names)}
    checked = base + [f"f_rest_{i}" for i in range(m)] + [e for e in EXTRAS + (FILTER_3D,) if e in present]
    _check_finite(path, _nonfinite(table[:, [where[q] for q in checked]], checked))

    def stack(keys: list[str]) -> np.ndarray:
        return np.ascontiguousarray(table[:, [where[q] for q in keys]])

    rest = stack([f"f_rest_{i}" for i in range(m)]).reshape(n, 3, k - 1).transpose(0, 2, 1)
    sh = np.concatenate([stack(["f_dc_0", "f_dc_1", "f_dc_2"])[:, None, :], rest], axis=1)
    extras = {e: stack([e])[:, 0] for e in EXTRAS if e in present}
    ignored = [q for q in names if q in NOT_RENDERED - {"nx", "ny", "nz"}]
    if ignored:
        meta["ignored"] = " ".join(ignored)
    scales, opacities = stack(["scale_0", "scale_1", "scale_2"]), stack(["opacity"])[:, 0]
    if FILTER_3D in present:
        scales, opacities = fold_filter_3d(path, scales, opacities, stack([FILTER_3D])[:, 0])
        meta[FILTER_3D] = FILTER_3D_NOTE
    for e, kind in ((e, meta.get(f"activation.{e}")) for e in extras):
        if kind is not None and kind not in ACTIVATIONS:
            raise PlyFormatError(path, f"comment 'smgs activation.{e} {kind}'", f"one of {list(ACTIVATIONS)}")
    out = PlySplats(stack(["x", "y", "z"]), np.ascontiguousarray(sh), opacities, scales,
                    stack(["rot_0", "rot_1", "rot_2", "rot_3"]), extras, meta)
    out.check(path)
    _check_activations(path, out)
    return out


def _check_rendered(path: Path, names: list[str], rendered: set[str]) -> None:
    """Every property is one smgs renders or one that does not change rendering (``NOT_RENDERED``):
    another is refused by name, since a model scored without it is another model."""
    unknown = [q for q in names if q not in rendered and q not in NOT_RENDERED]
    if unknown:
        raise PlyFormatError(path, f"properties smgs cannot render: {_short(unknown)} (a model that needs them, such "
                             "as a 4D or spacetime model's time and motion, would be scored as another model)",
                             "the 3DGS properties, with smgs's extras, Mip-Splatting's filter_3D, normals or "
                             "red/green/blue beside them; if those properties do not change how the model renders, "
                             "write the file without them")


def fold_filter_3d(path: Path, scales: np.ndarray, opacities: np.ndarray,
                   filter_3d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mip-Splatting's 3D smoothing filter folded into the Gaussians it filters, as its own
    ``save_fused_ply`` does for viewers: each scale becomes sqrt(s² + f²) and the opacity is multiplied
    by sqrt(Π s² / Π (s² + f²)) (the filtered Gaussian's peak), f the per-Gaussian filter_3D (a world
    length). Takes and returns raw values (log scales, opacity logits); computed in float64."""
    f = filter_3d.astype(np.float64)
    if (f < 0).any():
        i = int(np.flatnonzero(f < 0)[0])
        raise PlyFormatError(path, f"filter_3D has {int((f < 0).sum())} negative value(s) (vertex {i}: {f[i]:g})",
                             "filter_3D a world length ≥ 0 (Mip-Splatting's 3D filter size)")
    raw = scales.astype(np.float64)
    log_sum = 0.5 * np.log(np.exp(2 * raw) + f[:, None] ** 2)            # log sqrt(s² + f²)
    log_coef = (raw - log_sum).sum(axis=1)                                 # log sqrt(Π s² / Π (s² + f²))
    o = opacities.astype(np.float64)
    log_p = -np.logaddexp(0, -o) + log_coef                               # log(sigmoid(o) · coef)
    logit = log_p - np.log(-np.expm1(log_p))
    return log_sum.astype(np.float32), logit.astype(np.float32)


# exp overflows float32 above log(FLT_MAX) ≈ 88.72: a finite raw value that would render as inf
_EXP_MAX = float(np.log(np.finfo(np.float32).max))


def _check_activations(path: Path, s: PlySplats) -> None:
    """Raw values whose activation overflows (exp(scale_i) = inf in float32; α and β under exp) are
    refused naming the property, the count and the first vertex, instead of reaching the renderer as
    an unnamed inf. γ may be +inf (a hard depth cut), so it is not checked."""
    cols = {f"scale_{i}": s.scales[:, i] for i in range(3)}
    cols |= {e: s.extras[e] for e in ("gef_alpha", "softmax_beta")
             if e in s.extras and s.meta.get(f"activation.{e}", "exp") == "exp"}
    for name, raw in cols.items():
        over = np.flatnonzero(raw > _EXP_MAX)
        if over.size:
            i = int(over[0])
            raise PlyFormatError(path, f"property {name} has {over.size} value(s) above {_EXP_MAX:.2f}, whose exp "
                                 f"overflows float32 (vertex {i}: {name} = {float(raw[i]):g}, exp = inf)",
                                 f"{name} the log of a finite size (values up to {_EXP_MAX:.2f})")


def _meta(comments: list[str]) -> dict[str, str]:
    out = {}
    for c in comments:
        parts = c.split(maxsplit=2)
        if len(parts) >= 2 and parts[0] == _COMMENT:
            out[parts[1]] = parts[2] if len(parts) == 3 else ""
    return out


def _rest_index(path: Path, name: str) -> int:
    tail = name[len("f_rest_"):] if name.startswith("f_rest_") else ""
    if not tail.isdigit():
        raise PlyFormatError(path, f"misnamed property {name!r}", "f_rest_<index>")
    return int(tail)


def _degree(path: Path, m: int) -> int:
    """SH degree from the f_rest count M = 3·((d+1)² − 1)."""
    for d in range(MAX_SH_DEGREE + 1):
        if m == 3 * ((d + 1) ** 2 - 1):
            return d
    k = m / 3 + 1
    hint = (f" (degree {math.isqrt(int(k)) - 1}, above the renderer's {MAX_SH_DEGREE})"
            if m % 3 == 0 and math.isqrt(int(k)) ** 2 == int(k) else " (no SH degree)")
    raise PlyFormatError(path, f"{m} f_rest properties{hint}",
                         "0, 9, 24 or 45 (3·((degree+1)² − 1) for SH degree 0..3)")


def _columns(s: PlySplats) -> dict[str, np.ndarray]:
    return {"means": s.means, "sh": s.sh, "opacities": s.opacities, "scales": s.scales, "quats": s.quats,
            **s.extras}


def _nonfinite(table: np.ndarray, names: list[str]) -> dict[str, tuple[int, int]]:
    """name -> (NaN count, inf count) of the columns of ``table`` [N, P] that have any."""
    if np.isfinite(table).all():
        return {}
    nan, inf = np.isnan(table).sum(axis=0), np.isinf(table).sum(axis=0)
    return {q: (int(a), int(b)) for q, a, b in zip(names, nan, inf) if a or b}


def _check_finite(path: Path, bad: dict[str, tuple[int, int]], what: str = "finite values only") -> None:
    if bad:
        nan, inf = sum(b[0] for b in bad.values()), sum(b[1] for b in bad.values())
        where = ", ".join(f"{q}: {a} NaN, {b} inf" for q, (a, b) in list(bad.items())[:8])
        more = f", … {len(bad) - 8} more properties" if len(bad) > 8 else ""
        raise PlyFormatError(path, f"{nan} NaN and {inf} inf value(s) in {len(bad)} properties ({where}{more})",
                             what)


def _short(names: list[str], limit: int = 20) -> str:
    return " ".join(names[:limit]) + (f" … ({len(names)} in all)" if len(names) > limit else "")


_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
          "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


@dataclass
class _Header:
    """A PLY header as text, read without plyfile (which allocates what it declares)."""

    fmt: str
    elements: list[tuple[str, int, list[str]]]   # (name, declared count, property types; "list" for lists)
    body_start: int
    body_bytes: int

    def simple_row(self) -> int | None:
        """Bytes per vertex of a binary file with one element of scalar properties (else None)."""
        if not self.fmt.startswith("binary") or len(self.elements) != 1:
            return None
        types = self.elements[0][2]
        if not types or any(t not in _SIZES for t in types):
            return None
        return sum(_SIZES[t] for t in types)


def _header(path: Path) -> _Header | None:
    """The header of ``path``, parsed as text; None when it cannot be (plyfile then says why).
    A file that does not start with 'ply' is refused here, naming its first bytes."""
    with open(path, "rb") as f:
        head = f.read(1 << 20)
    if not (head.startswith(b"ply\n") or head.startswith(b"ply\r\n")):
        raise PlyFormatError(path, f"not a PLY file: it begins with {head[:16]!r}",
                             "'ply', then the format, the elements and 'end_header' as ASCII text")
    end = head.find(b"end_header")
    if end < 0 or head.find(b"\n", end) < 0:
        return None
    fmt, elements = "", []
    for line in head[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if parts[:1] == ["format"] and len(parts) >= 2:
            fmt = parts[1]
        elif parts[:1] == ["element"] and len(parts) == 3:
            try:
                elements.append((parts[1], int(parts[2]), []))
            except ValueError:
                return None
        elif parts[:1] == ["property"] and elements and len(parts) >= 3:
            elements[-1][2].append("list" if parts[1] == "list" else parts[1])
    body_start = head.index(b"\n", end) + 1
    return _Header(fmt, elements, body_start, path.stat().st_size - body_start)


def _check_sizes(path: Path, h: _Header | None) -> None:
    """What the header declares against the bytes the file has: an ASCII file too short for its
    declared rows (even at one character per value: 10^12 vertices claimed by a small file), a
    binary file or an ASCII file with data beyond the declared vertices (a header whose count is too
    small would have read part of the model silently)."""
    if h is None:
        return
    if h.fmt == "ascii":
        least = sum(count * 2 * max(1, len(types)) for _, count, types in h.elements)   # "v " per value
        if least > h.body_bytes:
            name, count, _ = max(h.elements, key=lambda e: e[1])
            raise PlyFormatError(path, f"the header declares {count} {name} rows, which need at least {least} bytes "
                                 f"as ASCII text; the file has {h.body_bytes} after its header",
                                 "an 'element' count no larger than the rows the file holds")
        if len(h.elements) == 1:
            with open(path, "rb") as f:
                f.seek(h.body_start)
                rows = sum(1 for line in f if line.strip())
            if rows > h.elements[0][1]:
                raise PlyFormatError(path, f"{rows} data rows, but the header declares {h.elements[0][1]} "
                                     f"{h.elements[0][0]} rows (the rest would be ignored)",
                                     "an 'element' count equal to the rows the file holds")
        return
    row = h.simple_row()
    if row is not None and h.body_bytes - h.elements[0][1] * row >= row:
        name, count, _ = h.elements[0]
        raise PlyFormatError(path, f"the header declares {count} {name} rows × {row} bytes = {count * row} bytes, "
                             f"but the file has {h.body_bytes} bytes of data (room for {h.body_bytes // row}); "
                             "the rest would be ignored", "an 'element' count that covers the file's data")


def _size_note(h: "_Header | None") -> str:
    """For a binary file with one scalar element (``h``, its parsed header): how many bytes the
    header asks for and how many there are (plyfile has already rejected the data)."""
    row = h.simple_row() if h is not None else None
    if row is None:
        return ""
    count, have = h.elements[0][1], h.body_bytes
    return (f": the header declares {count} vertices × {row} bytes = {count * row} bytes of data, the file "
            f"has {have} (room for {have // row} vertices)")
