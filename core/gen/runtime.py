"""Open ONNX model files with onnxruntime, validate them against their contract, run them.

    sess = load_model("models/forward_denoiser.onnx", kind="forward_denoiser", threads=2)
    out = sess.run(x_t=..., sigma=..., normal=..., ...)        # dict name -> float32 ndarray

* Sessions are cached per process (key: resolved path, file size and mtime, thread count), so a
  worker that keeps running (``brdf worker --no-fork``) keeps its models warm; a replaced file is
  re-validated and re-opened.
* onnxruntime gets explicit thread counts (``intra_op_num_threads = threads``,
  ``inter_op_num_threads = 1``, sequential execution, no spinning): it never takes more cores than
  asked, on machines shared with other work.
* :class:`core.errors.ModelLoadError` names the file and the problem for: a missing file, a file
  that is not a loadable ONNX model (corrupt / truncated), missing or wrong contract metadata, an
  incompatible contract version, a missing / extra / wrongly shaped input or output.
* :meth:`ModelSession.run` raises :class:`core.errors.ShapeError` for inputs that do not fit the
  contract and :class:`core.errors.NumericalError` naming the input for NaN/Inf; non-finite
  outputs raise :class:`NumericalError` naming the model file and the output.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.errors import ConfigError, ModelLoadError, NumericalError, ShapeError
from core.gen import contract as C

_ORT_TYPES = {"tensor(float)": "float32", "tensor(double)": "float64", "tensor(float16)": "float16",
              "tensor(int64)": "int64", "tensor(int32)": "int32"}

_CACHE: dict[tuple, "ModelSession"] = {}
_LOCK = threading.Lock()


@dataclass(frozen=True)
class ModelInfo:
    """What :func:`load_model` read from a validated file."""

    path: Path
    """The ONNX file."""
    contract: C.Contract
    """The contract the file satisfies."""
    version: tuple[int, int]
    """The file's contract version (same major as the code's, minor <= the code's)."""
    frames: int
    """Frames per window the model was trained with (``brdf.frames``)."""
    spatial_multiple: int
    """H and W are padded to multiples of this before running (``brdf.spatial_multiple``)."""
    sigma_data: float | None
    """EDM sigma_data (diffusion contracts), else None."""
    sigma_min: float | None
    """Smallest trained noise level (diffusion contracts), else None."""
    sigma_max: float | None
    """Largest trained noise level (diffusion contracts), else None."""
    metadata: dict
    """All ``metadata_props`` of the file."""
    input_names: tuple[str, ...] = ()
    """The graph inputs the file declares (the contract's, less optional ones it leaves out)."""

    def takes(self, name: str) -> bool:
        """True when the file declares input ``name`` (for optional contract inputs)."""
        return name in self.input_names


def _dims_of(arg) -> tuple:
    return tuple(d if isinstance(d, int) and d > 0 else None for d in arg.shape)


def _meta_int(meta: dict, key: str, path: Path, default: int | None = None, minimum: int = 1) -> int:
    if key not in meta:
        if default is not None:
            return default
        raise ModelLoadError(f"{path}: metadata {key!r} missing")
    try:
        v = int(meta[key])
    except ValueError:
        raise ModelLoadError(f"{path}: metadata {key!r} is not an integer: {meta[key]!r}") from None
    if v < minimum:
        raise ModelLoadError(f"{path}: metadata {key!r} must be >= {minimum}, got {v}")
    return v


def _meta_float(meta: dict, key: str, path: Path) -> float:
    if key not in meta:
        raise ModelLoadError(f"{path}: metadata {key!r} missing (required by diffusion contracts)")
    try:
        v = float(meta[key])
    except ValueError:
        raise ModelLoadError(f"{path}: metadata {key!r} is not a number: {meta[key]!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ModelLoadError(f"{path}: metadata {key!r} must be finite and > 0, got {v}")
    return v


def validate_session(sess, path: Path, kind: str | None = None) -> ModelInfo:
    """Check an onnxruntime session against its contract; :class:`ModelLoadError` naming ``path``
    and every mismatch found. ``kind``: the expected contract (None = whatever the file declares)."""
    meta = dict(sess.get_modelmeta().custom_metadata_map)
    declared = meta.get(C.META_CONTRACT)
    if declared is None:
        raise ModelLoadError(f"{path}: ONNX metadata has no {C.META_CONTRACT!r} (not a BRDFusion "
                             f"model, or exported without core.gen.nets.export_onnx)")
    if declared not in C.CONTRACTS:
        raise ModelLoadError(f"{path}: unknown contract {declared!r} (known: {sorted(C.CONTRACTS)})")
    if kind is not None and declared != kind:
        raise ModelLoadError(f"{path}: model implements contract {declared!r}, expected {kind!r}")
    con = C.CONTRACTS[declared]
    vtext = meta.get(C.META_VERSION)
    if vtext is None:
        raise ModelLoadError(f"{path}: metadata {C.META_VERSION!r} missing")
    try:
        ver = C.parse_version(vtext)
    except ValueError as e:
        raise ModelLoadError(f"{path}: metadata {C.META_VERSION!r}: {e}") from None
    if ver[0] != con.version[0] or ver[1] > con.version[1]:
        raise ModelLoadError(f"{path}: contract {declared} version {vtext} is not compatible with "
                             f"this code's version {con.version_str} (same major, minor <= "
                             f"{con.version[1]} needed)")
    problems: list[str] = []
    for what, specs, args in (("input", con.inputs, sess.get_inputs()), ("output", con.outputs, sess.get_outputs())):
        by_name = {a.name: a for a in args}
        for spec in specs:
            a = by_name.pop(spec.name, None)
            if a is None and spec.optional:
                continue
            if a is None:
                problems.append(f"{what} {spec.name!r} missing (has {sorted(x.name for x in args)})")
                continue
            dt = _ORT_TYPES.get(a.type, a.type)
            if dt != spec.dtype:
                problems.append(f"{what} {spec.name!r}: dtype {dt}, contract needs {spec.dtype}")
            dims = _dims_of(a)
            if len(dims) != spec.rank:
                problems.append(f"{what} {spec.name!r}: rank {len(dims)} {list(a.shape)}, contract "
                                f"needs rank {spec.rank} {list(spec.dims)}")
                continue
            for i, (got, want) in enumerate(zip(dims, spec.dims)):
                if isinstance(want, int) and got is not None and got != want:
                    problems.append(f"{what} {spec.name!r}: dimension {i} is {got}, contract needs "
                                    f"{want} ({list(spec.dims)})")
        if what == "input" and by_name:
            problems.append(f"extra input(s) {sorted(by_name)} not in contract {declared}")
    if problems:
        raise ModelLoadError(f"{path}: does not match contract {declared} v{con.version_str}: "
                             + "; ".join(problems))
    frames = _meta_int(meta, C.META_FRAMES, path, default=1)
    multiple = _meta_int(meta, C.META_MULTIPLE, path, default=1)
    sd = smin = smax = None
    if con.diffusion:
        sd = _meta_float(meta, C.META_SIGMA_DATA, path)
        smin = _meta_float(meta, C.META_SIGMA_MIN, path)
        smax = _meta_float(meta, C.META_SIGMA_MAX, path)
        if smin >= smax:
            raise ModelLoadError(f"{path}: metadata sigma_min {smin} >= sigma_max {smax}")
    return ModelInfo(path, con, ver, frames, multiple, sd, smin, smax, meta,
                     tuple(a.name for a in sess.get_inputs()))


class ModelSession:
    """A validated, warm onnxruntime session of one model file. Thread-safe ``run``."""

    def __init__(self, sess, info: ModelInfo, threads: int):
        self._sess = sess
        self.info = info
        self.threads = threads
        self._lock = threading.Lock()

    @property
    def path(self) -> Path:
        return self.info.path

    @property
    def kind(self) -> str:
        return self.info.contract.kind

    def _check_inputs(self, inputs: dict) -> tuple[dict[str, np.ndarray], dict[str, int]]:
        con = self.info.contract
        names = {s.name for s in con.inputs}
        extra = set(inputs) - names
        if extra:
            raise ShapeError(f"{self.path}: unknown input(s) {sorted(extra)} for contract {con.kind} "
                             f"(inputs: {[s.name for s in con.inputs]})")
        bound: dict[str, int] = {}
        arrays = {}
        for spec in con.inputs:
            if spec.optional and not self.info.takes(spec.name):
                continue  # the file was made without it: a fed value is ignored (contract docs)
            if spec.name not in inputs:
                extra_doc = f" (optional in the contract, but this model takes it: {spec.doc})" if spec.optional else ""
                raise ShapeError(f"{self.path}: input {spec.name!r} missing{extra_doc}")
            a = inputs[spec.name]
            if hasattr(a, "detach"):  # torch tensor
                a = a.detach().cpu().numpy()
            a = np.asarray(a)
            if a.dtype.kind not in "fiu":
                raise ShapeError(f"input {spec.name!r}: dtype {a.dtype} is not numeric")
            a = np.ascontiguousarray(a, dtype=np.float32)
            if not np.all(np.isfinite(a)):
                bad = int(a.size - np.count_nonzero(np.isfinite(a)))
                raise NumericalError(f"input {spec.name!r}: {bad} non-finite value(s) (NaN or Inf)")
            if a.ndim != spec.rank:
                raise ShapeError(f"input {spec.name!r}: expected shape {list(spec.dims)}, got {list(a.shape)}")
            for i, (got, want) in enumerate(zip(a.shape, spec.dims)):
                if isinstance(want, int):
                    if got != want:
                        raise ShapeError(f"input {spec.name!r}: dimension {i} must be {want} "
                                         f"({list(spec.dims)}), got {list(a.shape)}")
                elif bound.setdefault(want, got) != got:
                    raise ShapeError(f"input {spec.name!r}: dimension {want}={got} disagrees with "
                                     f"{want}={bound[want]} of an earlier input (shape {list(a.shape)})")
            arrays[spec.name] = a
        if "sigma" in arrays and np.any(arrays["sigma"] <= 0):
            raise NumericalError(f"input 'sigma': must be > 0, got min {float(arrays['sigma'].min())}")
        return arrays, bound

    def run(self, **inputs) -> dict[str, np.ndarray]:
        """Run the model on the contract's named inputs (numpy arrays or torch tensors, cast to
        float32); an optional contract input the file does not declare is ignored. Image inputs
        whose H, W are not multiples of ``spatial_multiple`` are padded by replication and the
        outputs cropped back. Returns {output name: float32 array}."""
        arrays, bound = self._check_inputs(inputs)
        m = self.info.spatial_multiple
        h, w = bound.get("H"), bound.get("W")
        ph = (-h) % m if h is not None else 0
        pw = (-w) % m if w is not None else 0
        if ph or pw:
            for spec in self.info.contract.inputs:
                if spec.dims[-2:] == ("H", "W") and spec.name in arrays:
                    pad = [(0, 0)] * (spec.rank - 2) + [(0, ph), (0, pw)]
                    arrays[spec.name] = np.pad(arrays[spec.name], pad, mode="edge")
        with self._lock:
            outs = self._sess.run(None, arrays)
        result = {}
        for arg, o in zip(self._sess.get_outputs(), outs):
            o = np.asarray(o, dtype=np.float32)
            if o.ndim >= 2 and (ph or pw) and self.info.contract.outputs and \
                    any(s.name == arg.name and s.dims[-2:] == ("H", "W") for s in self.info.contract.outputs):
                o = o[..., : o.shape[-2] - ph, : o.shape[-1] - pw]
            if not np.all(np.isfinite(o)):
                bad = int(o.size - np.count_nonzero(np.isfinite(o)))
                raise NumericalError(f"{self.path}: output {arg.name!r} has {bad} non-finite value(s)")
            result[arg.name] = np.ascontiguousarray(o)
        return result


def _open_session(path: Path, threads: int):
    try:
        import onnxruntime as ort
    except ImportError as e:  # pragma: no cover - hard dependency
        raise ModelLoadError(f"{path}: onnxruntime is not installed ({e})") from None
    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    # do not busy-wait between ops: the machines are shared (benchmarks, training, other jobs)
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    so.log_severity_level = 3
    try:
        return ort.InferenceSession(str(path), so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for bad files
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ModelLoadError(f"{path}: not a loadable ONNX model ({msg[:300]})") from None


def load_model(path: str | os.PathLike, kind: str | None = None, threads: int = 2) -> ModelSession:
    """Open (or reuse) a validated session of the ONNX file ``path``.

    Args:
        path: the .onnx file.
        kind: expected contract (``forward_denoiser``, ``inverse_gbuffer``, ``lighting``);
            None accepts any known contract.
        threads: onnxruntime intra-op threads (>= 1).

    Raises:
        ModelLoadError: missing, unreadable or corrupt file; contract or version mismatch
            (the message names the file and each mismatch).
        ConfigError: ``threads`` < 1 or unknown ``kind``.
    """
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"threads: must be an int >= 1, got {threads!r}")
    if kind is not None:
        C.get_contract(kind)
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise ModelLoadError(f"{p}: model file not found") from None
    except OSError as e:
        raise ModelLoadError(f"{p}: cannot read model file ({e.strerror})") from None
    if not p.is_file():
        raise ModelLoadError(f"{p}: not a regular file")
    if st.st_size == 0:
        raise ModelLoadError(f"{p}: model file is empty")
    key = (str(p.resolve()), st.st_size, st.st_mtime_ns, threads)
    with _LOCK:
        cached = _CACHE.get(key)
    if cached is not None:
        if kind is not None and cached.kind != kind:
            raise ModelLoadError(f"{p}: model implements contract {cached.kind!r}, expected {kind!r}")
        return cached
    sess = _open_session(p, threads)
    info = validate_session(sess, p, kind)
    ms = ModelSession(sess, info, threads)
    with _LOCK:
        # drop stale sessions of the same file (replaced on disk)
        for k in [k for k in _CACHE if k[0] == key[0] and k != key]:
            del _CACHE[k]
        _CACHE[key] = ms
    return ms


def clear_cache() -> None:
    """Forget every cached session (tests; a worker that wants to free memory)."""
    with _LOCK:
        _CACHE.clear()
