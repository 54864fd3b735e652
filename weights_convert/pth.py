"""Safe reader for PyTorch `.pth` checkpoints and pickled NumPy weights, without torch.

`load_pth` reads both formats `torch.save` has written since torch 0.4:

* the zip format (torch >= 1.6 default): `<top>/data.pkl` plus one record `<top>/data/<key>`
  per storage, and `<top>/byteorder` ("little" or "big");
* the legacy format (`_use_new_zipfile_serialization=False`, e.g. MonoDepth2's 2019
  `mono_640x192/*.pth`): consecutive pickles (magic number, protocol version 1001, sys info,
  the object, the list of storage keys), then per storage an int64 little-endian element
  count and the raw little-endian bytes.

`load_pickle` reads a plain pickle of NumPy arrays (detectron2 / Mask2Former `.pkl` weights,
Python 2 ones included).

Nothing is imported from torch and no pickled global is resolved by import: `find_class`
looks the `module.qualname` up in an explicit allow-list whose entries are our own stand-ins
(storage types, torch dtypes, tensor rebuild functions returning NumPy arrays), plain container
types, and NumPy's array/dtype/scalar reconstruction. Anything else (`os.system`, a model
class, ...) raises `ForbiddenGlobalError` before it can be called.
"""

from __future__ import annotations

import _compat_pickle
import codecs
import collections
import io
import os
import pickle
import struct
import zipfile
from typing import Any, BinaryIO, Callable

import ml_dtypes  # A jax dependency; gives NumPy the bfloat16 / float8 dtypes torch has.
import numpy as np

try:  # NumPy >= 2.
  from numpy._core.multiarray import _reconstruct as _np_reconstruct
  from numpy._core.multiarray import scalar as _np_scalar
except ImportError:  # NumPy 1.x.
  from numpy.core.multiarray import _reconstruct as _np_reconstruct
  from numpy.core.multiarray import scalar as _np_scalar

__all__ = ["CheckpointError", "ForbiddenGlobalError", "checked_path", "load_pickle", "load_pth"]

# Pickled as an int by the legacy format's first pickle (torch/serialization.py).
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001
_ZIP_MAGIC = b"PK\x03\x04"  # A zip's first local file header.
_LEGACY_NOT_PICKLE = "a legacy torch checkpoint, not a plain pickle (use load_pth)"
# what a file in the other converters' formats is, and the flag that reads it
_PLAIN_PICKLE_HINT = " (detectron2 .pkl weights: `--from detectron2` where the converter has it)"
_SAFETENSORS = ("not a PyTorch checkpoint but a safetensors file (Hugging Face weights: "
                "`--from hf` where the converter has it)")

# torch dtype name (as `torch.<name>` pickles it) -> NumPy dtype of the returned array.
_DTYPES: dict[str, np.dtype] = {
    "float32": np.dtype(np.float32),
    "float64": np.dtype(np.float64),
    "float16": np.dtype(np.float16),
    "bfloat16": np.dtype(ml_dtypes.bfloat16),
    "complex64": np.dtype(np.complex64),
    "complex128": np.dtype(np.complex128),
    "int64": np.dtype(np.int64),
    "int32": np.dtype(np.int32),
    "int16": np.dtype(np.int16),
    "int8": np.dtype(np.int8),
    "uint8": np.dtype(np.uint8),
    "uint16": np.dtype(np.uint16),
    "uint32": np.dtype(np.uint32),
    "uint64": np.dtype(np.uint64),
    "bool": np.dtype(np.bool_),
    "float8_e4m3fn": np.dtype(ml_dtypes.float8_e4m3fn),
    "float8_e5m2": np.dtype(ml_dtypes.float8_e5m2),
    "float8_e4m3fnuz": np.dtype(ml_dtypes.float8_e4m3fnuz),
    "float8_e5m2fnuz": np.dtype(ml_dtypes.float8_e5m2fnuz),
}

# Legacy typed storage class (`torch.FloatStorage`, `torch.cuda.FloatStorage`) -> dtype name.
_STORAGE_DTYPES: dict[str, str] = {
    "FloatStorage": "float32",
    "DoubleStorage": "float64",
    "HalfStorage": "float16",
    "BFloat16Storage": "bfloat16",
    "ComplexFloatStorage": "complex64",
    "ComplexDoubleStorage": "complex128",
    "LongStorage": "int64",
    "IntStorage": "int32",
    "ShortStorage": "int16",
    "CharStorage": "int8",
    "ByteStorage": "uint8",
    "BoolStorage": "bool",
}


class CheckpointError(Exception):
  """A checkpoint could not be read; the message names the file and the problem."""


class ForbiddenGlobalError(CheckpointError):
  """The pickle references a global outside the allow-list (nothing of it was called).

  Attributes:
    path: the file.
    global_name: the refused `module.qualname`, e.g. `posix.system`.
  """

  def __init__(self, path: str, global_name: str):
    self.path = path
    self.global_name = global_name
    super().__init__(
        f"{path}: forbidden global '{global_name}' in the pickle; only tensors, plain "
        "containers and NumPy arrays may be loaded, so the file was refused")


class _FormatError(Exception):
  """Internal: a malformed file; turned into `CheckpointError` with the path prepended."""


# ----------------------------------------------------------------------------------------------
# Stand-ins that allowed globals resolve to. Frozen (no attribute assignment, no __dict__), so a
# pickle's BUILD opcode cannot alter them for later loads.


class _Frozen:
  __slots__ = ()

  def __setattr__(self, name: str, value: Any) -> None:
    raise AttributeError(f"{type(self).__name__} is read-only")

  def _init(self, **fields: Any) -> None:
    for name, value in fields.items():
      object.__setattr__(self, name, value)


class _StorageType(_Frozen):
  """`torch.FloatStorage` etc.; `dtype_name` is None for `torch.UntypedStorage` (bytes)."""
  __slots__ = ("qualname", "dtype_name")

  def __init__(self, qualname: str, dtype_name: str | None):
    self._init(qualname=qualname, dtype_name=dtype_name)


class _TorchDtype(_Frozen):
  """`torch.float32` etc., as passed to `_rebuild_tensor_v3`."""
  __slots__ = ("name",)

  def __init__(self, name: str):
    self._init(name=name)


class _Function(_Frozen):
  """A callable allowed global; wraps one of our functions."""
  __slots__ = ("qualname", "fn")

  def __init__(self, qualname: str, fn: Callable[..., Any]):
    self._init(qualname=qualname, fn=fn)

  def __call__(self, *args: Any) -> Any:
    return self.fn(*args)


class _NdarrayType(_Frozen):
  """`numpy.ndarray` as a token: only `_reconstruct` accepts it, it constructs nothing."""
  __slots__ = ()


_NDARRAY = _NdarrayType()


class _Storage(_Frozen):
  """One storage a persistent id refers to, or a view of it (legacy format).

  Attributes:
    key: the storage's key in the file.
    dtype_name: element type of a typed storage; None for an untyped (byte) storage.
    raw: the storage's bytes, exactly as in the file; None while only the structure of a
      legacy file is read (first pass).
    big_endian: whether `raw` is big-endian.
    offset, length: the view's first element and element count (whole storage: 0, None).
    cache: per-load cache `(key, dtype name) -> decoded flat array`.
  """
  __slots__ = ("key", "dtype_name", "raw", "big_endian", "offset", "length", "cache")

  def __init__(self, key: str, dtype_name: str | None, raw: bytes | None, big_endian: bool,
               cache: dict[tuple[str, str], np.ndarray], offset: int = 0,
               length: int | None = None):
    self._init(key=key, dtype_name=dtype_name, raw=raw, big_endian=big_endian, offset=offset,
               length=length, cache=cache)

  def flat(self, dtype_name: str) -> np.ndarray:
    """The storage (or view) decoded as a read-only 1-D array of `dtype_name`."""
    cache_key = (self.key, dtype_name)
    full = self.cache.get(cache_key)
    if full is None:
      dtype = _DTYPES[dtype_name]
      if len(self.raw) % dtype.itemsize:
        raise _FormatError(f"storage '{self.key}' has {len(self.raw)} bytes, not a multiple of "
                           f"the {dtype_name} item size {dtype.itemsize}")
      if self.big_endian and dtype.itemsize > 1:
        swapped = np.frombuffer(self.raw, np.uint8).reshape(-1, dtype.itemsize)[:, ::-1]
        full = np.ascontiguousarray(swapped).view(dtype).reshape(-1)
        full.flags.writeable = False
      else:
        full = np.frombuffer(self.raw, dtype)
      self.cache[cache_key] = full
    stop = None if self.length is None else self.offset + self.length
    return full[self.offset:stop]


# ----------------------------------------------------------------------------------------------
# Tensor rebuild functions (torch/_utils.py signatures), returning NumPy arrays.


def _is_int(x: Any) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def _tensor(storage: Any, storage_offset: Any, size: Any, stride: Any,
            dtype_name: str | None) -> np.ndarray | None:
  """`storage[storage_offset:]` viewed with `size`/`stride` (in elements), copied contiguous."""
  if not isinstance(storage, _Storage):
    raise _FormatError(f"a tensor's storage is a {type(storage).__name__}, not a storage")
  dtype_name = dtype_name or storage.dtype_name
  if dtype_name is None:
    raise _FormatError(f"tensor on untyped storage '{storage.key}' has no dtype")
  size, stride = tuple(size), tuple(stride)
  if not (_is_int(storage_offset) and all(_is_int(x) for x in size + stride)
          and len(size) == len(stride)):
    raise _FormatError(f"tensor on storage '{storage.key}' has invalid geometry "
                       f"offset={storage_offset!r} size={size!r} stride={stride!r}")
  if storage_offset < 0 or min(size + stride, default=0) < 0:
    raise _FormatError(f"tensor on storage '{storage.key}' has a negative offset, size or stride")
  if storage.raw is None:  # First pass over a legacy file: structure only.
    return None
  flat = storage.flat(dtype_name)
  if 0 in size:
    return np.zeros(size, flat.dtype)
  last = storage_offset + sum((n - 1) * s for n, s in zip(size, stride))
  if last >= flat.size:
    raise _FormatError(
        f"tensor of size {size}, stride {stride}, offset {storage_offset} reads element {last} "
        f"of storage '{storage.key}', which has {flat.size} {dtype_name} elements")
  view = np.lib.stride_tricks.as_strided(
      flat[storage_offset:], shape=size, strides=tuple(s * flat.itemsize for s in stride),
      writeable=False)
  return np.array(view, order="C", copy=True)


def _apply_metadata(array: np.ndarray | None, metadata: Any) -> np.ndarray | None:
  """Applies the lazy `conj` / `neg` bits torch stores beside a tensor's data."""
  if array is None or not metadata:
    return array
  if not isinstance(metadata, dict):
    raise _FormatError(f"tensor metadata is a {type(metadata).__name__}, not a dict")
  if metadata.get("conj"):
    array = np.conj(array)
  if metadata.get("neg"):
    array = np.negative(array)
  return array


def _rebuild_tensor(storage: Any, storage_offset: Any, size: Any, stride: Any) -> Any:
  return _tensor(storage, storage_offset, size, stride, None)


def _rebuild_tensor_v2(storage: Any, storage_offset: Any, size: Any, stride: Any,
                       requires_grad: Any, backward_hooks: Any, metadata: Any = None) -> Any:
  del requires_grad, backward_hooks  # Training-time state; not part of the weights.
  return _apply_metadata(_tensor(storage, storage_offset, size, stride, None), metadata)


def _rebuild_tensor_v3(storage: Any, storage_offset: Any, size: Any, stride: Any,
                       requires_grad: Any, backward_hooks: Any, dtype: Any,
                       metadata: Any = None) -> Any:
  del requires_grad, backward_hooks
  if not isinstance(dtype, _TorchDtype):
    raise _FormatError(f"_rebuild_tensor_v3 got dtype {dtype!r}, not a torch dtype")
  return _apply_metadata(_tensor(storage, storage_offset, size, stride, dtype.name), metadata)


def _rebuild_parameter(data: Any, requires_grad: Any, backward_hooks: Any) -> Any:
  del requires_grad, backward_hooks
  return data  # An nn.Parameter is its data.


def _rebuild_parameter_with_state(data: Any, requires_grad: Any, backward_hooks: Any,
                                  state: Any) -> Any:
  del requires_grad, backward_hooks, state
  return data


# ----------------------------------------------------------------------------------------------
# Plain-container and NumPy reconstruction stand-ins.


def _safe_bytes(*args: Any) -> bytes:
  """`bytes()` / `bytes(iterable)` / `bytes(str, encoding)` but never `bytes(n)` (a huge alloc)."""
  if args and _is_int(args[0]):
    raise _FormatError("refused bytes(int) in the pickle")
  return bytes(*args)


def _safe_bytearray(*args: Any) -> bytearray:
  if args and _is_int(args[0]):
    raise _FormatError("refused bytearray(int) in the pickle")
  return bytearray(*args)


_TEXT_ENCODINGS = ("latin1", "latin-1", "iso-8859-1", "iso8859-1", "utf-8", "utf8", "ascii")


def _codecs_encode(obj: Any, encoding: str = "utf-8", errors: str = "strict") -> bytes:
  """`_codecs.encode` as protocol-2 pickles use it for bytes, limited to text encodings."""
  if not (isinstance(obj, str) and isinstance(encoding, str)
          and encoding.lower().replace("_", "-") in _TEXT_ENCODINGS
          and errors in ("strict", "surrogateescape")):
    raise _FormatError(f"refused _codecs.encode({type(obj).__name__}, {encoding!r})")
  return codecs.encode(obj, encoding, errors)


def _reconstruct(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
  if subtype is not _NDARRAY or tuple(shape) != (0,):  # What ndarray.__reduce__ writes.
    raise _FormatError(f"numpy _reconstruct{(subtype, shape)!r:.80}; only an ndarray of "
                       "shape (0,) is allowed (BUILD then fills it)")
  return _np_reconstruct(np.ndarray, shape, dtype)


def _frombuffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
  """NumPy's protocol-5 array reconstruction (`numpy._core.numeric._frombuffer`)."""
  if not isinstance(buf, (bytes, bytearray, pickle.PickleBuffer)) or not isinstance(
      dtype, np.dtype) or dtype.hasobject:
    raise _FormatError("invalid numpy _frombuffer arguments in the pickle")
  return np.frombuffer(buf, dtype).reshape(shape, order=order)


def _scalar(dtype: Any, *args: Any) -> Any:
  if not isinstance(dtype, np.dtype):
    raise _FormatError(f"numpy scalar of {dtype!r}, not a dtype")
  return _np_scalar(dtype, *args)


def _functions(table: dict[str, Callable[..., Any]]) -> dict[str, _Function]:
  return {name: _Function(name, fn) for name, fn in table.items()}


_CONTAINER_GLOBALS: dict[str, Any] = {
    "collections.OrderedDict": collections.OrderedDict,
    "builtins.set": set,
    "builtins.frozenset": frozenset,
    **_functions({
        "builtins.bytes": _safe_bytes,
        "builtins.bytearray": _safe_bytearray,
        "_codecs.encode": _codecs_encode,
    }),
}

_TORCH_GLOBALS: dict[str, Any] = {
    **_functions({
        "torch._utils._rebuild_tensor": _rebuild_tensor,
        "torch._utils._rebuild_tensor_v2": _rebuild_tensor_v2,
        "torch._utils._rebuild_tensor_v3": _rebuild_tensor_v3,
        "torch._utils._rebuild_parameter": _rebuild_parameter,
        "torch._utils._rebuild_parameter_with_state": _rebuild_parameter_with_state,
    }),
    **{f"{module}.{cls}": _StorageType(f"{module}.{cls}", dtype_name)
       for cls, dtype_name in _STORAGE_DTYPES.items() for module in ("torch", "torch.cuda")},
    "torch.UntypedStorage": _StorageType("torch.UntypedStorage", None),
    "torch.storage.UntypedStorage": _StorageType("torch.storage.UntypedStorage", None),
    **{f"torch.{name}": _TorchDtype(name) for name in _DTYPES},
}

_NUMPY_GLOBALS: dict[str, Any] = {
    "numpy.ndarray": _NDARRAY,
    "numpy.dtype": np.dtype,
    **_functions({
        f"numpy.{core}.{name}": fn
        for core in ("core", "_core")
        for name, fn in (("multiarray._reconstruct", _reconstruct), ("multiarray.scalar", _scalar),
                         ("numeric._frombuffer", _frombuffer))
    }),
}


def _allowed(*, torch: bool, numpy: bool) -> dict[str, Any]:
  return {**_CONTAINER_GLOBALS, **(_TORCH_GLOBALS if torch else {}),
          **(_NUMPY_GLOBALS if numpy else {})}


class _RestrictedUnpickler(pickle.Unpickler):
  """Unpickler whose globals come only from `allowed`; `latin1` decodes Python 2 strings."""

  def __init__(self, file: BinaryIO, *, path: str, allowed: dict[str, Any],
               persistent_load: Callable[[Any], Any] | None = None):
    super().__init__(file, encoding="latin1")
    self._path = path
    self._allowed = allowed
    self._persistent_load = persistent_load

  def find_class(self, module: str, name: str) -> Any:
    # Python 2 names (`__builtin__.set`, `copy_reg...`), as the default find_class maps them.
    if (module, name) in _compat_pickle.NAME_MAPPING:
      module, name = _compat_pickle.NAME_MAPPING[(module, name)]
    elif module in _compat_pickle.IMPORT_MAPPING:
      module = _compat_pickle.IMPORT_MAPPING[module]
    qualname = f"{module}.{name}"
    try:
      return self._allowed[qualname]
    except KeyError:
      raise ForbiddenGlobalError(self._path, qualname) from None

  def persistent_load(self, pid: Any) -> Any:
    if self._persistent_load is None:
      raise _FormatError("persistent id in a plain pickle (is it a torch checkpoint?)")
    return self._persistent_load(pid)


def _unpickle(file: BinaryIO, path: str, allowed: dict[str, Any],
              persistent_load: Callable[[Any], Any] | None = None) -> Any:
  return _RestrictedUnpickler(file, path=path, allowed=allowed,
                              persistent_load=persistent_load).load()


def _resolve_bare_storages(obj: Any, memo: dict[int, Any]) -> Any:
  """Replaces storages saved on their own (not inside a tensor) by copies of their 1-D data.

  Dicts and lists are updated in place (keeping OrderedDict attributes such as `_metadata`),
  tuples, sets and frozensets rebuilt when something in them changed.
  """
  if isinstance(obj, _Storage):
    return np.array(obj.flat(obj.dtype_name or "uint8"), copy=True)
  if not isinstance(obj, (dict, list, tuple, set, frozenset)):
    return obj
  if id(obj) in memo:
    return memo[id(obj)]
  memo[id(obj)] = obj
  if isinstance(obj, dict):
    for key in list(obj):
      obj[key] = _resolve_bare_storages(obj[key], memo)
  elif isinstance(obj, list):
    obj[:] = [_resolve_bare_storages(item, memo) for item in obj]
  else:
    items = [_resolve_bare_storages(item, memo) for item in obj]
    if any(new is not old for new, old in zip(items, obj)):
      memo[id(obj)] = type(obj)(items)
  return memo[id(obj)]


# ----------------------------------------------------------------------------------------------
# Zip format.


def _zip_prefix(zf: zipfile.ZipFile) -> str:
  """The archive's top folder with trailing '/' ('' if `data.pkl` is at the root)."""
  names = zf.namelist()
  tops = [n[:-len("data.pkl")] for n in names
          if n == "data.pkl" or (n.endswith("/data.pkl") and n.count("/") == 1)]
  if len(tops) != 1:
    raise _FormatError(f"not a PyTorch checkpoint: zip archive with {len(tops)} top-level "
                       "data.pkl records (expected 1)")
  prefix = tops[0]
  if f"{prefix}constants.pkl" in names:
    raise _FormatError("TorchScript archive (torch.jit.save) is not supported; save and load a "
                       "state_dict instead")
  return prefix


def _load_zip(path: str, allow_numpy: bool) -> Any:
  with zipfile.ZipFile(path) as zf:
    prefix = _zip_prefix(zf)
    names = set(zf.namelist())
    big_endian = False
    if f"{prefix}byteorder" in names:
      order = zf.read(f"{prefix}byteorder").strip()
      if order not in (b"little", b"big"):
        raise _FormatError(f"unknown byteorder {order!r}")
      big_endian = order == b"big"
    raws: dict[str, bytes] = {}
    cache: dict[tuple[str, str], np.ndarray] = {}

    def persistent_load(pid: Any) -> _Storage:
      if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"):
        raise _FormatError(f"unsupported persistent id {pid!r:.80}")
      _, storage_type, key, _location, numel = pid
      if not isinstance(storage_type, _StorageType) or not _is_int(numel) or numel < 0:
        raise _FormatError(f"invalid storage record {pid!r:.80}")
      key = str(key)
      itemsize = 1 if storage_type.dtype_name is None else _DTYPES[
          storage_type.dtype_name].itemsize
      if key not in raws:
        name = f"{prefix}data/{key}"
        if name not in names:
          raise _FormatError(f"storage record '{name}' is missing from the zip archive")
        raws[key] = zf.read(name)
      if len(raws[key]) != numel * itemsize:
        raise _FormatError(
            f"storage '{key}' has {len(raws[key])} bytes but {numel} x {itemsize}-byte "
            f"{storage_type.dtype_name or 'byte'} elements were declared")
      return _Storage(key, storage_type.dtype_name, raws[key], big_endian, cache)

    data = io.BytesIO(zf.read(f"{prefix}data.pkl"))
    obj = _unpickle(data, path, _allowed(torch=True, numpy=allow_numpy), persistent_load)
  return _resolve_bare_storages(obj, {})


# ----------------------------------------------------------------------------------------------
# Legacy format.


def _read_exact(f: BinaryIO, n: int, what: str) -> bytes:
  data = f.read(n)
  if len(data) != n:
    raise _FormatError(f"truncated file: {what} needs {n} bytes, only {len(data)} left")
  return data


def _load_legacy(path: str, f: BinaryIO, allow_numpy: bool) -> Any:
  """Reads a legacy-format file positioned after its magic number."""
  plain = _allowed(torch=False, numpy=False)
  protocol = _unpickle(f, path, plain)
  if protocol != _LEGACY_PROTOCOL:
    raise _FormatError(f"unsupported legacy protocol version {protocol!r}")
  sys_info = _unpickle(f, path, plain)
  if not isinstance(sys_info, dict):
    raise _FormatError("legacy header has no sys_info dict")
  # torch writes and reads legacy storage data little-endian whatever sys_info says.
  allowed = _allowed(torch=True, numpy=allow_numpy)
  main_start = f.tell()
  declared: dict[str, tuple[str, int]] = {}
  raws: dict[str, bytes] = {}
  cache: dict[tuple[str, str], np.ndarray] = {}

  def persistent_load(pid: Any) -> _Storage:
    if isinstance(pid, tuple) and pid and pid[0] == "module":
      raise _FormatError("the file pickles a whole nn.Module; only state dicts and tensors "
                         "are supported")
    if not (isinstance(pid, tuple) and len(pid) == 6 and pid[0] == "storage"):
      raise _FormatError(f"unsupported persistent id {pid!r:.80}")
    _, storage_type, key, _location, numel, view = pid
    if not isinstance(storage_type, _StorageType) or not _is_int(numel) or numel < 0:
      raise _FormatError(f"invalid storage record {pid!r:.80}")
    if storage_type.dtype_name is None:  # torch.load cannot read these either.
      raise _FormatError("untyped storage in a legacy-format file is not supported")
    key = str(key)
    if declared.setdefault(key, (storage_type.dtype_name, numel)) != (
        storage_type.dtype_name, numel):
      raise _FormatError(f"storage '{key}' is declared with two dtypes or sizes")
    offset, length = 0, None
    if view is not None:
      if not (isinstance(view, tuple) and len(view) == 3 and _is_int(view[1])
              and _is_int(view[2]) and view[1] >= 0 and view[2] >= 0
              and view[1] + view[2] <= numel):
        raise _FormatError(f"invalid storage view {view!r:.80} of storage '{key}'")
      offset, length = view[1], view[2]
    return _Storage(key, storage_type.dtype_name, raws.get(key), False, cache, offset, length)

  # Pass 1: the object's structure, to learn each storage's dtype; the data follows it.
  _unpickle(f, path, allowed, persistent_load)
  keys = _unpickle(f, path, plain)
  if not isinstance(keys, list):
    raise _FormatError("legacy storage key list is missing")
  for key in map(str, keys):
    if key not in declared:
      raise _FormatError(f"storage '{key}' has data but no tensor refers to it")
    dtype_name, numel = declared[key]
    (count,) = struct.unpack("<q", _read_exact(f, 8, f"element count of storage '{key}'"))
    if count != numel:
      raise _FormatError(f"storage '{key}' holds {count} elements but {numel} were declared")
    raws[key] = _read_exact(f, numel * _DTYPES[dtype_name].itemsize, f"storage '{key}'")
  missing = sorted(set(declared) - set(raws))
  if missing:
    raise _FormatError(f"storage data missing for keys {missing[:5]}")
  # Pass 2: the same pickle again, now with the data.
  f.seek(main_start)
  return _resolve_bare_storages(_unpickle(f, path, allowed, persistent_load), {})


# ----------------------------------------------------------------------------------------------
def _is_safetensors(path: str, head: bytes) -> bool:
  """The file starts as a safetensors file does: a u64 header size within the file, then `{`."""
  return len(head) >= 9 and head[8:9] == b"{" and \
      8 < int.from_bytes(head[:8], "little") < os.path.getsize(path)


# Public API.


def checked_path(path: str | os.PathLike) -> str:
  """`path` as a string; CheckpointError (one line) when it is missing or not a regular file."""
  path = os.fspath(path)
  if not os.path.exists(path):
    raise CheckpointError(f"{path}: no such file")
  if not os.path.isfile(path):
    raise CheckpointError(f"{path}: not a regular file")
  return path


def _reraise(path: str, error: Exception) -> CheckpointError:
  """Wraps any non-CheckpointError failure into a one-line CheckpointError for `path`."""
  if isinstance(error, _FormatError):
    return CheckpointError(f"{path}: {error}")
  if isinstance(error, zipfile.BadZipFile):
    return CheckpointError(f"{path}: truncated or corrupt zip archive ({error})")
  detail = str(error).splitlines()[0] if str(error) else ""
  return CheckpointError(
      f"{path}: truncated or corrupt pickle data ({type(error).__name__}: {detail})")


def load_pth(path: str | os.PathLike, *, allow_numpy: bool = True) -> Any:
  """Loads a `torch.save` file (zip or legacy format) without torch, tensors as NumPy arrays.

  Args:
    path: the `.pth` / `.pt` / `.ckpt` file.
    allow_numpy: also allow NumPy arrays/scalars pickled inside the checkpoint.

  Returns:
    The saved object: every tensor (and nn.Parameter) becomes a C-contiguous, writeable NumPy
    array of the tensor's dtype, shape and values (views are resolved; bfloat16/float8 use
    `ml_dtypes`); dicts (OrderedDict with its `_metadata` attribute), lists, tuples, sets,
    numbers, strings, bools and None are kept.

  Raises:
    ForbiddenGlobalError: the pickle references a global outside the allow-list.
    CheckpointError: missing, truncated, corrupt or unsupported file.
  """
  path = checked_path(path)
  try:
    with open(path, "rb") as f:
      head = f.read(512)
      if head.startswith(_ZIP_MAGIC):  # torch writes the first record at offset 0.
        return _load_zip(path, allow_numpy)
      if len(head) >= 262 and head[257:262] == b"ustar":
        raise _FormatError("legacy tar checkpoint (torch < 0.4) is not supported; re-save it "
                           "with a newer torch")
      if _is_safetensors(path, head):
        raise _FormatError(_SAFETENSORS)
      if not head.startswith(b"\x80"):
        raise _FormatError("not a PyTorch checkpoint (neither a zip archive nor a legacy pickle)")
      f.seek(0)
      try:
        magic = _unpickle(f, path, _allowed(torch=False, numpy=False))
      except Exception:  # e.g. a NumPy array: the first object of a plain pickle, not a number
        magic = None
      if not (_is_int(magic) and magic == _LEGACY_MAGIC):
        raise _FormatError(f"not a PyTorch checkpoint: a plain pickle without torch's magic "
                           f"number{_PLAIN_PICKLE_HINT}")
      return _load_legacy(path, f, allow_numpy)
  except CheckpointError:
    raise
  except Exception as error:  # Anything a malformed file can raise while being decoded.
    raise _reraise(path, error) from error


def load_pth_or_pickle(path: str | os.PathLike, *, allow_numpy: bool = True) -> Any:
  """`load_pth` of a torch.save file (zip or legacy), else `load_pickle` of a plain pickle: told
  apart by the file's content, not its suffix (detectron2 writes `.pkl` pickles, a training
  script `.pth` / `.pt` / `.ckpt` torch files)."""
  path = checked_path(path)
  with open(path, "rb") as f:
    head = f.read(4)
  if head == _ZIP_MAGIC:
    return load_pth(path, allow_numpy=allow_numpy)
  try:
    return load_pickle(path, allow_numpy=allow_numpy)
  except CheckpointError as error:
    if not str(error).endswith(_LEGACY_NOT_PICKLE):
      raise
  return load_pth(path, allow_numpy=allow_numpy)


# the training-size entries a MonoDepth2-family encoder file carries beside its tensors
METADATA_KEYS = ("height", "width", "use_stereo")
# the prefixes a wrapped model's `state_dict()` puts before every name: `module.` of
# nn.DataParallel / DistributedDataParallel, `_orig_mod.` of a `torch.compile`d model (either
# inside the other, in any order)
WRAPPER_PREFIXES = ("module.", "_orig_mod.")
# where training scripts put the state dict: {"state_dict": sd, "epoch": ...}, {"model": sd,
# "optimizer": ...}, and PyTorch's checkpoint recipe {"model_state_dict": sd,
# "optimizer_state_dict": ..., "epoch": ..., "loss": loss}
WRAPPER_KEYS = ("state_dict", "model", "model_state_dict")


def load_state_dict(path: str | os.PathLike) -> dict:
  """`load_pth` of a file that must hold a state dict (name -> tensor, plus metadata entries).

  Two common ways of saving one are undone: a state dict stored under one of `WRAPPER_KEYS`
  of a dict that holds no weight itself (a training script's checkpoint; a scalar tensor beside
  it, such as the recipe's `loss`, is no weight), and the `module.` / `_orig_mod.` prefixes of
  a DataParallel or compiled model (`strip_data_parallel`)."""
  return unwrap_state_dict(load_pth(path), path)


def unwrap_state_dict(state: Any, path: str | os.PathLike) -> dict:
  """`load_state_dict`'s unwrapping of an object `load_pth` read from `path`."""
  if not isinstance(state, dict):
    raise CheckpointError(f"{path}: expected a state dict, found a {type(state).__name__}")
  wrapped = [k for k in WRAPPER_KEYS if isinstance(state.get(k), dict)]
  if wrapped and not any(isinstance(v, np.ndarray) and v.ndim > 0 for v in state.values()):
    state = state[wrapped[0]]
  check_names(state, path)
  return strip_data_parallel(state, str(path))


def check_names(state: dict, path: str | os.PathLike) -> None:
  """CheckpointError naming the file when a key of the state dict is not a string: a state
  dict's keys are parameter names (`load_state_dict` takes nothing else)."""
  odd = [k for k in state if not isinstance(k, str)][:1]
  if odd:
    odd = odd[0]
    raise CheckpointError(f"{path}: key {odd!r} ({type(odd).__name__}) is not a parameter "
                          f"name; expected a state dict (name -> tensor)")


def is_safetensors_file(path: str | os.PathLike) -> bool:
  """Whether the file is a safetensors file by its content, whatever its name (a Hub cache
  blob has none)."""
  with open(path, "rb") as f:
    head = f.read(16)
  return _is_safetensors(os.fspath(path), head)


def strip_data_parallel(state: dict, path: str) -> dict:
  """Removes the `WRAPPER_PREFIXES` that every non-metadata key carries (a DataParallel save,
  a compiled model's, one inside the other), outermost first."""
  while True:
    keys = [k for k in state if k not in METADATA_KEYS]
    for prefix in WRAPPER_PREFIXES:
      prefixed = {k for k in keys if isinstance(k, str) and k.startswith(prefix)}
      if prefixed:
        break
    else:
      return state
    if len(prefixed) != len(keys):
      plain = sorted(map(str, set(keys) - set(prefixed)))
      raise CheckpointError(f"{path}: {len(prefixed)} keys start with {prefix!r} and "
                            f"{len(plain)} do not (e.g. {plain[0]}); expected all or none")
    state = {(k[len(prefix):] if k in prefixed else k): v for k, v in state.items()}


_REQUIRED = object()


def flag_entry(state: dict, key: str, path: str | os.PathLike) -> bool:
  """A boolean metadata entry (`use_stereo`, upstream's `opt.use_stereo`), False when absent;
  a bool, 0 or 1 (also as a one-element array). Anything else (the text 'False', which `bool`
  reads as true) is refused, naming the file."""
  value = state.get(key, False)
  if isinstance(value, np.ndarray) and value.size == 1:
    value = value.item()
  if not isinstance(value, (bool, int, np.bool_, np.integer)) or value not in (0, 1):
    raise CheckpointError(f"{path}: its {key!r} entry is {value!r}, expected True or False")
  return bool(value)


def int_entry(state: dict, key: str, path: str | os.PathLike, default: Any = _REQUIRED) -> Any:
  """A positive-integer metadata entry of a state dict (e.g. encoder.pth's "height"), as int.

  Absent: `default` (CheckpointError when none is given). A one-element tensor is accepted;
  anything else that is not a positive int (a bool, a float, a string) is a CheckpointError.
  """
  if key not in state:
    if default is _REQUIRED:
      raise CheckpointError(f"{path}: has no {key!r} entry")
    return default
  value = state[key]
  if isinstance(value, np.ndarray) and value.size == 1:
    value = value.item()
  if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
    raise CheckpointError(f"{path}: extra entry {key!r} = {value!r} is not a positive int")
  return int(value)


def unpickle_arrays(stream: BinaryIO, name: str) -> Any:
  """Unpickles a stream that may hold only containers, numbers, strings and NumPy arrays (the
  allow-list of `load_pickle`), e.g. the object array inside a `.npz` member.

  Raises:
    ForbiddenGlobalError: the pickle references a global outside the allow-list.
  """
  return _unpickle(stream, name, _allowed(torch=False, numpy=True))


def load_pickle(path: str | os.PathLike, *, allow_numpy: bool = True) -> Any:
  """Loads a plain pickle (e.g. detectron2 / Mask2Former `.pkl` weights) with the allow-list.

  Python 2 pickles are read with `encoding="latin1"` (as detectron2 does), which NumPy needs
  for arrays pickled by Python 2.

  Args:
    path: the pickle file.
    allow_numpy: allow NumPy arrays, dtypes and scalars (numpy 1.x `numpy.core` and 2.x
      `numpy._core` names).

  Returns:
    The unpickled object (containers, numbers, strings and NumPy arrays).

  Raises:
    ForbiddenGlobalError: the pickle references a global outside the allow-list.
    CheckpointError: missing, truncated or corrupt file, or a torch checkpoint.
  """
  path = checked_path(path)
  try:
    with open(path, "rb") as f:
      head = f.read(16)
      if head.startswith(_ZIP_MAGIC):
        raise _FormatError("a zip archive, not a plain pickle (a torch checkpoint? use load_pth)")
      if _is_safetensors(path, head):
        raise _FormatError(_SAFETENSORS)
      f.seek(0)
      obj = _unpickle(f, path, _allowed(torch=False, numpy=allow_numpy))
    if _is_int(obj) and obj == _LEGACY_MAGIC:
      raise _FormatError(_LEGACY_NOT_PICKLE)
    return obj
  except CheckpointError:
    raise
  except Exception as error:
    raise _reraise(path, error) from error
