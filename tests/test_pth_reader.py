"""Tests for `weights_convert.pth`, the torch-free `.pth` / `.pkl` reader.

Reference: torch itself. Every fixture is written with `torch.save` (zip and legacy format)
into tmp_path and the arrays `load_pth` returns are compared exactly with `tensor.numpy()`.
The security tests craft pickles whose reduce calls `os.system` and check that nothing ran.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import pickletools
import struct
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import hypothesis
import hypothesis.strategies as st
import ml_dtypes
import numpy as np
import pytest
import torch

from weights_convert.pth import CheckpointError, ForbiddenGlobalError, load_pickle, load_pth

FORMATS = ("zip", "legacy")
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _save(obj: Any, path: Path, fmt: str) -> Path:
  torch.save(obj, path, _use_new_zipfile_serialization=(fmt == "zip"))
  return path


def _assert_tensor_equal(got: Any, ref: torch.Tensor) -> None:
  want = ref.detach().resolve_conj().resolve_neg().numpy()
  assert isinstance(got, np.ndarray), type(got)
  assert got.dtype == want.dtype, (got.dtype, want.dtype)
  assert got.shape == want.shape, (got.shape, want.shape)
  assert got.flags.c_contiguous and got.flags.writeable
  np.testing.assert_array_equal(got, want)


def _assert_tree_equal(got: Any, ref: Any) -> None:
  """`got` (from load_pth) matches `ref` (torch.load / the saved object) exactly."""
  if isinstance(ref, torch.Tensor):
    _assert_tensor_equal(got, ref)
  elif isinstance(ref, dict):
    assert type(got) is type(ref), (type(got), type(ref))
    assert list(got) == list(ref)
    for key in ref:
      _assert_tree_equal(got[key], ref[key])
    assert getattr(got, "_metadata", None) == getattr(ref, "_metadata", None)
  elif isinstance(ref, (list, tuple)):
    assert type(got) is type(ref) and len(got) == len(ref)
    for g, r in zip(got, ref):
      _assert_tree_equal(g, r)
  else:
    assert type(got) is type(ref) and got == ref, (got, ref)


def _small_net_state_dict() -> collections.OrderedDict:
  torch.manual_seed(0)
  net = torch.nn.Sequential(
      torch.nn.Conv2d(3, 4, 3, bias=False), torch.nn.BatchNorm2d(4), torch.nn.ReLU(),
      torch.nn.Conv2d(4, 2, 1))
  net.train()
  net(torch.randn(2, 3, 6, 6))  # Moves running stats and num_batches_tracked off defaults.
  return net.state_dict()


def _rewrite_zip(src: Path, dst: Path, replace: dict[str, bytes | None]) -> None:
  """Copies a zip, replacing members (`None` drops one); names are without the top folder."""
  with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_STORED) as zout:
    for name in zin.namelist():
      short = name.split("/", 1)[1]
      data = replace.get(short, zin.read(name))
      if data is not None:
        zout.writestr(name, data)


class _Evil:
  """Unpickling this runs `touch <marker>`, if the unpickler lets it."""

  def __init__(self, marker: Path):
    self.marker = marker

  def __reduce__(self):
    return (os.system, (f"touch {self.marker}",))


def _system_global() -> str:
  return f"{os.system.__module__}.system"  # "posix.system" on Linux.


# ----------------------------------------------------------------------------------------------
# Parity with torch.


@pytest.mark.parametrize("fmt", FORMATS)
def test_conv_bn_state_dict_matches_torch(tmp_path, fmt):
  state = _small_net_state_dict()
  path = _save(state, tmp_path / "net.pth", fmt)
  got = load_pth(path)
  _assert_tree_equal(got, torch.load(path))
  assert got["1.num_batches_tracked"].dtype == np.int64 and got["1.num_batches_tracked"] == 1
  assert got["0.weight"].shape == (4, 3, 3, 3)


@pytest.mark.parametrize("fmt", FORMATS)
def test_monodepth2_style_dict_with_extras(tmp_path, fmt):
  obj = dict(_small_net_state_dict())
  obj.update(height=192, width=640, use_stereo=False, name="mono_640x192", lr=1e-4,
             scales=[0, 1, 2, 3], shape=(192, 640), nothing=None, blob=b"\x00\xffab")
  path = _save(obj, tmp_path / "encoder.pth", fmt)
  got = load_pth(path)
  _assert_tree_equal(got, obj)
  assert got["height"] == 192 and got["width"] == 640 and got["use_stereo"] is False


@pytest.mark.parametrize("fmt", FORMATS)
def test_dtypes(tmp_path, fmt):
  x = torch.linspace(-3, 3, 12).reshape(3, 4)
  obj = {
      "f16": x.half(), "f32": x, "f64": x.double(), "i64": (x * 7).long(),
      "i32": (x * 7).int(), "i16": (x * 7).short(), "i8": (x * 7).to(torch.int8),
      "u8": torch.arange(250, 256, dtype=torch.uint8), "bool": x > 0,
      "c64": torch.complex(x, -x), "c128": torch.complex(x.double(), x.double()),
      "u16": torch.tensor([0, 1, 65535]).to(torch.uint16),  # _rebuild_tensor_v3 (zip).
  }
  if fmt == "legacy":
    del obj["u16"]  # torch's legacy writer has no storage class for uint16.
  path = _save(obj, tmp_path / "dtypes.pth", fmt)
  _assert_tree_equal(load_pth(path), obj)


@pytest.mark.parametrize("fmt", FORMATS)
def test_bfloat16_is_exact(tmp_path, fmt):
  ref = torch.tensor([1.0, -2.5, 3.14159, 1e-3, 65504.0]).bfloat16()
  got = load_pth(_save({"w": ref}, tmp_path / "bf16.pth", fmt))["w"]
  assert got.dtype == ml_dtypes.bfloat16
  np.testing.assert_array_equal(got.astype(np.float32), ref.float().numpy())


@pytest.mark.parametrize("fmt", FORMATS)
def test_views_strides_offsets_and_shared_storage(tmp_path, fmt):
  big = torch.arange(24, dtype=torch.float32)
  obj = {
      "transposed": big.reshape(4, 6).t(),
      "slice": big.reshape(4, 6)[1:3, ::2],
      "expanded": torch.tensor([1.0, 2.0, 3.0]).expand(2, 3),  # Stride 0.
      "channels_last": big.reshape(1, 2, 3, 4).contiguous(memory_format=torch.channels_last),
      "shared_a": big[2:5],
      "shared_b": big.view(2, 12)[1],
      "scalar": torch.tensor(7.5),
      "scalar_int": torch.tensor(3),
      "empty": torch.empty(0, 3),
      "param": torch.nn.Parameter(torch.ones(2, 2) * 0.5),
  }
  path = _save(obj, tmp_path / "views.pth", fmt)
  got = load_pth(path)
  _assert_tree_equal(got, obj)
  got["shared_a"][0] = -1.0  # Independent copies, although they share a storage in the file.
  assert got["shared_b"][0] == 12.0 and got["transposed"][2, 0] == 2.0


@pytest.mark.parametrize("fmt", FORMATS)
def test_view_with_offset_saved_alone(tmp_path, fmt):
  big = torch.arange(10.0)
  path = _save(big[3:7], tmp_path / "offset.pth", fmt)  # torch saves all 10 elements.
  got = load_pth(path)
  _assert_tensor_equal(got, big[3:7])


@pytest.mark.parametrize("fmt", FORMATS)
def test_bare_storage_and_nested_containers(tmp_path, fmt):
  t = torch.arange(5, dtype=torch.int32)
  typed = torch.tensor([-1, 2, 3], dtype=torch.int16)
  obj = {"nested": [{"t": t, "pair": (t[1:], 2)}],
         "typed": torch.storage.TypedStorage(wrap_storage=typed.untyped_storage(),
                                             dtype=torch.int16, _internal=True)}
  if fmt == "zip":  # torch cannot load an untyped storage from the legacy format either.
    obj["untyped"] = torch.tensor([1.5, 2.0]).untyped_storage()
  got = load_pth(_save(obj, tmp_path / "nested.pth", fmt))
  _assert_tree_equal(got["nested"], obj["nested"])
  _assert_tensor_equal(got["typed"], typed)
  if fmt == "zip":
    np.testing.assert_array_equal(got["untyped"],
                                  np.array([1.5, 2.0], np.float32).view(np.uint8))


@hypothesis.settings(max_examples=25, deadline=None)
@hypothesis.given(
    shape=st.lists(st.integers(1, 4), min_size=1, max_size=4),
    data=st.data(),
    dtype=st.sampled_from([torch.float32, torch.float16, torch.int64, torch.uint8]),
    fmt=st.sampled_from(FORMATS))
def test_random_views_match_torch(shape, data, dtype, fmt):
  """Random permutations and stepped slices of a tensor survive save/load unchanged."""
  base = torch.arange(int(np.prod(shape)), dtype=torch.float64).reshape(shape).to(dtype)
  perm = data.draw(st.permutations(range(len(shape))))
  view = base.permute(*perm)
  index = tuple(
      slice(data.draw(st.integers(0, n - 1)), None, data.draw(st.integers(1, 2)))
      for n in view.shape)
  view = view[index]
  with tempfile.TemporaryDirectory() as tmp:
    path = _save({"v": view, "base": base}, Path(tmp) / "v.pth", fmt)
    got = load_pth(path)
  _assert_tensor_equal(got["v"], view)
  _assert_tensor_equal(got["base"], base)


def test_big_endian_zip_is_byteswapped(tmp_path):
  ref = collections.OrderedDict(
      a=torch.linspace(-1, 1, 6).reshape(2, 3), b=torch.tensor([1, -2, 2**40]),
      c=torch.tensor([0.5, -0.25]).half(), d=torch.tensor([1, 2, 255], dtype=torch.uint8))
  src = _save(ref, tmp_path / "le.pth", "zip")
  itemsizes = {"0": 4, "1": 8, "2": 2, "3": 1}  # Storage keys in the order of pickling.
  with zipfile.ZipFile(src) as zf:
    top = zf.namelist()[0].split("/")[0]
    swapped = {
        f"data/{k}": np.frombuffer(zf.read(f"{top}/data/{k}"), f"<u{n}").byteswap().tobytes()
        for k, n in itemsizes.items()}
  dst = tmp_path / "be.pth"
  _rewrite_zip(src, dst, {"byteorder": b"big", **swapped})
  got = load_pth(dst)
  _assert_tree_equal(got, ref)
  _assert_tree_equal(got, torch.load(dst))  # torch agrees that this is the big-endian file.


def test_reader_does_not_import_torch(tmp_path):
  path = _save(_small_net_state_dict(), tmp_path / "net.pth", "legacy")
  code = ("import sys; from weights_convert.pth import load_pth; "
          f"load_pth({str(path)!r}); assert 'torch' not in sys.modules, 'torch imported'")
  subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def _str(text: str) -> bytes:
  return b"X" + struct.pack("<I", len(text)) + text.encode()


def _ints(*values: int) -> bytes:
  return b"(" + b"".join(b"J" + struct.pack("<i", v) for v in values) + b"t"


def _tensor_pickle(key: str, numel: int, offset: int, size: tuple[int, ...],
                   stride: tuple[int, ...], legacy_view: bytes | None = None) -> bytes:
  """Hand-written `_rebuild_tensor_v2` pickle of a float32 tensor (what torch.save emits)."""
  pid = b"(" + _str("storage") + b"ctorch\nFloatStorage\n" + _str(key) + _str("cpu")
  pid += b"J" + struct.pack("<i", numel)
  if legacy_view is not None:
    pid += legacy_view
  return (b"\x80\x02ctorch._utils\n_rebuild_tensor_v2\n(" + pid + b"tQ"
          + b"J" + struct.pack("<i", offset) + _ints(*size) + _ints(*stride)
          + b"\x89ccollections\nOrderedDict\n)RtR.")


def _write_zip(path: Path, data_pkl: bytes, storages: dict[str, bytes]) -> Path:
  with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
    zf.writestr("archive/data.pkl", data_pkl)
    zf.writestr("archive/byteorder", b"little")
    zf.writestr("archive/version", b"3\n")
    for key, raw in storages.items():
      zf.writestr(f"archive/data/{key}", raw)
  return path


def _legacy_header() -> bytes:
  return b"".join(pickle.dumps(x, protocol=2) for x in (
      _LEGACY_MAGIC, 1001, {"protocol_version": 1001, "little_endian": True}))


def test_hand_written_tensor_pickle_matches_torch(tmp_path):
  """Checks the hand-written pickle used below: torch and load_pth read the same tensor."""
  raw = np.arange(8, dtype=np.float32).tobytes()
  path = _write_zip(tmp_path / "ok.pth", _tensor_pickle("0", 8, 1, (2, 3), (1, 2)), {"0": raw})
  want = np.arange(8, dtype=np.float32)[1:][np.arange(2)[:, None] + 2 * np.arange(3)[None, :]]
  np.testing.assert_array_equal(load_pth(path), want)
  _assert_tensor_equal(load_pth(path), torch.load(path))


@pytest.mark.parametrize("offset, size, stride, message", [
    (5, (4,), (1,), "reads element 8 of storage '0', which has 8"),
    (0, (3, 3), (3, 1), "reads element 8 of storage '0', which has 8"),
    (0, (2,), (9,), "reads element 9"),
    (-1, (2,), (1,), "negative"),
    (2, (2,), (-1,), "negative"),
    (0, (2, 2), (1,), "invalid geometry"),
])
def test_tensor_geometry_outside_storage_is_refused(tmp_path, offset, size, stride, message):
  """A tensor reading past its storage must fail (as_strided would read foreign memory)."""
  raw = np.arange(8, dtype=np.float32).tobytes()
  path = _write_zip(tmp_path / "bad.pth", _tensor_pickle("0", 8, offset, size, stride),
                    {"0": raw})
  with pytest.raises(CheckpointError, match=message):
    load_pth(path)


def test_legacy_storage_view_metadata(tmp_path):
  """Old torch pickled storage views as (view_key, offset, view_size); torch still reads them."""
  view = b"(" + _str("v") + b"J" + struct.pack("<i", 2) + b"J" + struct.pack("<i", 6) + b"t"
  main = _tensor_pickle("root", 10, 1, (3,), (2,), legacy_view=view)
  raw = np.arange(10, dtype=np.float32).tobytes()
  path = tmp_path / "view.pth"
  path.write_bytes(_legacy_header() + main + pickle.dumps(["root"], protocol=2)
                   + struct.pack("<q", 10) + raw)
  got = load_pth(path)
  np.testing.assert_array_equal(got, np.arange(10, dtype=np.float32)[2:8][1::2])  # [3, 5, 7]
  _assert_tensor_equal(got, torch.load(path, weights_only=False))
  bad = b"(" + _str("v") + b"J" + struct.pack("<i", 6) + b"J" + struct.pack("<i", 6) + b"t"
  path.write_bytes(_legacy_header() + _tensor_pickle("root", 10, 0, (1,), (1,), bad)
                   + pickle.dumps(["root"], protocol=2) + struct.pack("<q", 10) + raw)
  with pytest.raises(CheckpointError, match="invalid storage view"):
    load_pth(path)


# ----------------------------------------------------------------------------------------------
# Security: forbidden globals are refused before anything runs.


@pytest.mark.parametrize("fmt", FORMATS)
def test_os_system_in_checkpoint_is_refused(tmp_path, fmt):
  marker = tmp_path / "pwned_x"
  evil_pickle = pickle.dumps(
      collections.OrderedDict(w=1, payload=_Evil(marker)), protocol=2)
  path = tmp_path / "evil.pth"
  if fmt == "zip":
    _rewrite_zip(_save(_small_net_state_dict(), tmp_path / "good.pth", "zip"), path,
                 {"data.pkl": evil_pickle})
  else:
    path.write_bytes(_legacy_header() + evil_pickle + pickle.dumps([], protocol=2))
  with pytest.raises(ForbiddenGlobalError) as info:
    load_pth(path)
  assert info.value.global_name == _system_global()
  assert _system_global() in str(info.value) and str(path) in str(info.value)
  assert not marker.exists()


@pytest.mark.parametrize("protocol", [2, 4])
def test_os_system_in_plain_pickle_is_refused(tmp_path, protocol):
  marker = tmp_path / "pwned_x"
  path = tmp_path / "evil.pkl"
  path.write_bytes(pickle.dumps({"model": {}, "x": _Evil(marker)}, protocol=protocol))
  with pytest.raises(ForbiddenGlobalError, match=_system_global()):
    load_pickle(path)
  assert not marker.exists()


def test_model_class_global_is_refused(tmp_path):
  """A whole pickled nn.Module references its class: refused, naming it."""
  path = _save(torch.nn.Linear(2, 2), tmp_path / "module.pth", "zip")
  with pytest.raises(ForbiddenGlobalError, match="torch.nn.modules.linear.Linear"):
    load_pth(path)


# ----------------------------------------------------------------------------------------------
# Malformed files.


def test_missing_file(tmp_path):
  with pytest.raises(CheckpointError, match="no such file"):
    load_pth(tmp_path / "nope.pth")
  with pytest.raises(CheckpointError, match="no such file"):
    load_pickle(tmp_path / "nope.pkl")


def test_not_a_checkpoint(tmp_path):
  text = tmp_path / "notes.pth"
  text.write_text("hello\n")
  npy = tmp_path / "array.pth"
  np.save(npy.with_suffix(".npy"), np.zeros(3))
  npy.with_suffix(".npy").rename(npy)
  plain = tmp_path / "plain.pth"
  plain.write_bytes(pickle.dumps({"a": 1}, protocol=2))
  for path in (text, npy, plain):
    with pytest.raises(CheckpointError, match="not a PyTorch checkpoint") as info:
      load_pth(path)
    assert str(path) in str(info.value)
  zipped = tmp_path / "other.zip"
  with zipfile.ZipFile(zipped, "w") as zf:
    zf.writestr("readme.txt", "x")
  with pytest.raises(CheckpointError, match="not a PyTorch checkpoint"):
    load_pth(zipped)


@pytest.mark.parametrize("fmt", FORMATS)
def test_truncated_file(tmp_path, fmt):
  full = _save(_small_net_state_dict(), tmp_path / "full.pth", fmt).read_bytes()
  for cut in (len(full) // 2, len(full) - 3, 100):
    path = tmp_path / f"cut{cut}.pth"
    path.write_bytes(full[:cut])
    with pytest.raises(CheckpointError, match="truncated") as info:
      load_pth(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_zip_storage_with_wrong_length(tmp_path):
  src = _save(_small_net_state_dict(), tmp_path / "good.pth", "zip")
  with zipfile.ZipFile(src) as zf:
    top = zf.namelist()[0].split("/")[0]
    short = zf.read(f"{top}/data/0")[:-4]
  path = tmp_path / "bad.pth"
  _rewrite_zip(src, path, {"data/0": short})
  with pytest.raises(CheckpointError, match="storage '0' has .* bytes but 108 x 4-byte"):
    load_pth(path)


def test_legacy_storage_with_wrong_count(tmp_path):
  data = _save({"w": torch.ones(5)}, tmp_path / "good.pth", "legacy").read_bytes()
  stream = io.BytesIO(data)
  for _ in range(5):  # magic, protocol, sys_info, object, key list: skip without executing.
    for _ in pickletools.genops(stream):
      pass
  at = stream.tell()
  assert struct.unpack("<q", data[at:at + 8]) == (5,)
  path = tmp_path / "bad.pth"
  path.write_bytes(data[:at] + struct.pack("<q", 4) + data[at + 8:])
  with pytest.raises(CheckpointError, match="holds 4 elements but 5 were declared"):
    load_pth(path)


def test_zip_missing_storage_record(tmp_path):
  src = _save(_small_net_state_dict(), tmp_path / "good.pth", "zip")
  path = tmp_path / "bad.pth"
  _rewrite_zip(src, path, {"data/3": None})
  with pytest.raises(CheckpointError, match="data/3' is missing"):
    load_pth(path)


def test_legacy_tar_format_is_reported_unsupported(tmp_path):
  path = tmp_path / "old.pth"
  with tarfile.open(path, "w", format=tarfile.PAX_FORMAT) as tar:
    for name in ("storages", "tensors", "pickle"):
      payload = pickle.dumps(0, protocol=2)
      info = tarfile.TarInfo(name)
      info.size = len(payload)
      tar.addfile(info, io.BytesIO(payload))
  with pytest.raises(CheckpointError, match="tar checkpoint .* not supported"):
    load_pth(path)


# ----------------------------------------------------------------------------------------------
# Plain pickles (detectron2 .pkl weights).


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_load_pickle_detectron2_style(tmp_path, protocol):
  obj = {"model": {"a": np.arange(6, dtype=np.float32).reshape(2, 3),
                   "b": np.array([1, 2], dtype=np.int64), "f": np.asfortranarray(np.eye(3))},
         "__author__": "x", "matching_heuristics": True, "n": np.float64(2.5),
         "names": np.array(["ab", "c"]), "raw": b"", "set": {1, 2}}
  path = tmp_path / "model_final.pkl"
  path.write_bytes(pickle.dumps(obj, protocol=protocol))
  got = load_pickle(path)
  assert list(got) == list(obj) and got["__author__"] == "x"
  assert got["matching_heuristics"] is True and got["raw"] == b"" and got["set"] == {1, 2}
  for key, want in obj["model"].items():
    assert got["model"][key].dtype == want.dtype
    np.testing.assert_array_equal(got["model"][key], want)
  assert got["n"] == 2.5 and got["n"].dtype == np.float64
  np.testing.assert_array_equal(got["names"], obj["names"])


class _Py2Pickler(pickle._Pickler):
  """Writes bytes as Python 2 `str` (BINSTRING), as Python 2 detectron2 pickles hold them."""

  dispatch = pickle._Pickler.dispatch.copy()

  def _save_py2_str(self, obj: bytes) -> None:
    self.write(pickle.BINSTRING + struct.pack("<i", len(obj)) + obj)
    self.memoize(obj)

  dispatch[bytes] = _save_py2_str


def test_load_pickle_python2_numpy1_names(tmp_path):
  """numpy 1.x module names (`numpy.core`), `__builtin__` and latin-1 Python 2 strings."""
  obj = {"model": {"w": np.arange(4, dtype=np.float32)}, "s": np.int64(3),
         "author": b"caf\xe9", "tags": {1, 2}}
  buf = io.BytesIO()
  _Py2Pickler(buf, protocol=2).dump(obj)
  data = buf.getvalue().replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
  assert b"cnumpy.core.multiarray\n_reconstruct" in data and b"c__builtin__\nset" in data
  path = tmp_path / "py2.pkl"
  path.write_bytes(data)
  got = load_pickle(path)
  np.testing.assert_array_equal(got["model"]["w"], obj["model"]["w"])
  assert got["model"]["w"].dtype == np.float32 and got["s"] == 3 and got["tags"] == {1, 2}
  assert got["author"] == "caf\xe9"  # A Python 2 str, decoded as latin-1 (detectron2 does too).


def test_the_wrong_format_is_named_with_the_flag_that_reads_it(tmp_path):
  """A safetensors file (Hugging Face) or a plain pickle of NumPy arrays (detectron2's .pkl)
  given where a torch.save file is read, and a safetensors file where a pickle is: each says
  what the file is and which --from reads it (was: a forbidden-global refusal of numpy's
  `_reconstruct`, or 'truncated or corrupt pickle')."""
  from safetensors.numpy import save_file
  st = tmp_path / "model.safetensors"
  save_file({"w": np.ones((2, 3), np.float32)}, str(st))
  pkl = tmp_path / "model_final.pkl"
  pkl.write_bytes(pickle.dumps({"model": {"w": np.ones(3)}, "__author__": "d2"}, protocol=4))
  with pytest.raises(CheckpointError, match=r"model\.safetensors: not a PyTorch checkpoint but a "
                                            r"safetensors file .*`--from hf`"):
    load_pth(st)
  with pytest.raises(CheckpointError, match=r"model\.safetensors: not a PyTorch checkpoint but a "
                                            r"safetensors file"):
    load_pickle(st)
  with pytest.raises(CheckpointError, match=r"model_final\.pkl: not a PyTorch checkpoint: a plain "
                                            r"pickle .*`--from detectron2`"):
    load_pth(pkl)


def test_load_pickle_rejects_torch_checkpoints_and_garbage(tmp_path):
  path = _save({"w": torch.ones(2)}, tmp_path / "w.pth", "zip")
  with pytest.raises(CheckpointError, match="use load_pth"):
    load_pickle(path)
  truncated = tmp_path / "cut.pkl"
  truncated.write_bytes(pickle.dumps({"model": {"a": np.ones(100)}}, protocol=4)[:200])
  with pytest.raises(CheckpointError, match="truncated or corrupt"):
    load_pickle(truncated)


def test_a_deeper_resnet_encoder_is_named_as_unsupported():
  """A ResNet-101 / 152 encoder.pth (upstream's ResnetEncoder builds them) was taken for a
  ResNet-50 and then refused by the key table; it is named by its block count."""
  from weights_convert.monodepth2 import infer_num_layers
  bottleneck = lambda n3: {**{"encoder.layer1.0.conv3.weight": 0},
                           **{f"encoder.layer3.{i}.conv1.weight": 0 for i in range(n3)}}
  assert infer_num_layers(bottleneck(6), "e.pth") == 50
  for n3, name in ((23, "ResNet-101"), (36, "ResNet-152")):
    with pytest.raises(CheckpointError, match=f"e.pth: a {name} encoder .encoder.layer3 has "
                                              f"{n3} Bottleneck blocks.; ResNet-18, 34 and 50"):
      infer_num_layers(bottleneck(n3), "e.pth")
  basic = {f"encoder.layer3.{i}.conv1.weight": 0 for i in range(6)}
  assert infer_num_layers(basic, "e.pth") == 34


@pytest.mark.parametrize("fmt", ["zip", "legacy"])
def test_a_lazily_negated_tensor_loads_negated(tmp_path, fmt):
  """torch saves a negative view (`torch._neg_view`) with its storage and a `neg` flag: the
  values are the negated storage, as torch.load gives them."""
  ref = {"w": torch._neg_view(torch.tensor([1.0, -2.0, 3.5]))}
  assert ref["w"].is_neg()
  path = _save(ref, tmp_path / "neg.pth", fmt)
  got = load_pth(path)
  np.testing.assert_array_equal(got["w"], np.float32([-1.0, 2.0, -3.5]))
  _assert_tensor_equal(got["w"], torch.load(path)["w"])


def test_a_state_dict_key_that_is_not_a_name_is_one_line_naming_the_file(tmp_path):
  """A checkpoint whose dict has a non-string key (an int beside the tensors) is refused with
  one line naming the file by every converter's reader (it had been an AttributeError
  traceback in MonoDepth2's, HR-Depth's, Lite-Mono's and SGDepth's, and 'expected string or
  bytes-like object' naming no file in the others), through the CLI with exit 2."""
  from weights_convert.mask2former import read_checkpoint
  from weights_convert.pth import unwrap_state_dict
  path = tmp_path / "encoder.pth"
  torch.save({"encoder.conv1.weight": torch.zeros(64, 3, 7, 7), 1: torch.zeros(1)}, path)
  with pytest.raises(CheckpointError, match=f"^{path}: key 1 \\(int\\) is not a parameter name"):
    unwrap_state_dict(load_pth(path), path)
  with pytest.raises(CheckpointError, match=f"^{path}: key 1 \\(int\\) is not a parameter name"):
    read_checkpoint(path, "detectron2")
  with pytest.raises(CheckpointError, match=f"^{path}: key None \\(NoneType\\) is not"):
    unwrap_state_dict({"a": np.zeros(1), None: np.zeros(1)}, path)
  for args in (["monodepth2", "--encoder", str(path), "--depth", str(path)],
               ["sgdepth", "--model", str(path)], ["litemono", "--encoder", str(path),
                                                   "--depth", str(path)]):
    run = subprocess.run([sys.executable, "-m", "weights_convert", *args, "--out",
                          str(tmp_path / "out")], capture_output=True, text=True)
    assert run.returncode == 2 and run.stderr.startswith(f"error: {path}: key 1 (int) is not"), (
        args, run.stderr[-500:])
    assert run.stderr.count("\n") == 1, run.stderr
