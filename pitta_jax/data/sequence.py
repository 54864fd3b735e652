"""A lazily loaded sequence of frames: the common return type of every dataset reader.

Readers resolve a dataset's layout into a list of `FrameFiles` (paths only, cheap, so that a
missing file is reported when the dataset is opened), and `FrameSequence` reads a frame's files
when it is indexed: a 500-frame subset never sits in memory.

Besides the frames, a `FrameSequence` says what a method may rely on before any frame is read:
whether its order is capture order (`temporal`: consecutive frames of one or more recordings,
what methods reprojecting the previous frame need), where one recording ends and the next
begins (`FrameFiles.recording`: such a method never pairs frames across the cut), which frames
carry a camera matrix (`FrameFiles.intrinsics`), how to supply what is missing (`remedies`, for
one-line errors), what the reader chose on its own (`notes`, e.g. the only image size present),
and the dataset's own evaluation protocol where it has one (`evaluation`, e.g. the Garg crop of KITTI's
Eigen split).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import overload

import numpy as np

from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Frame
from pitta_jax.data.image_io import check_image_file, read_image
from pitta_jax.data.panoptic_io import PanopticRef


@dataclasses.dataclass(frozen=True)
class FrameFiles:
  """The files of one frame.

  name: the frame's stable identifier (`Frame.name`).
  image: the colour image file.
  depth: a loader returning (Hd, Wd) float32 metres (0 = invalid), or None without ground truth.
  depth_file: what `depth` reads (a file, or an archive's entry), named in errors
    (`Frame.depth_file`).
  panoptic: the panoptic files, or None.
  size: the (H, W) the image must have (e.g. from a calibration file), or None.
  size_source: the file that fixes `size`, named when the image disagrees.
  intrinsics: the camera matrix K (3, 3) of the image, or None.
  intrinsics_size: the (H, W) that `intrinsics` belongs to, or None (= the image's own size);
    K is scaled to the image when they differ (e.g. a full-size calibration for half-size
    images), refused when the aspect ratios differ by more than 1%.
  intrinsics_source: the calibration file `intrinsics` came from, named in errors.
  recording: the recording (drive, sequence) the frame was captured in. Where it changes between
    neighbours, the later frame starts a recording (`Frame.starts_recording`): methods that use
    the previous frame do not pair it with the last frame of the recording before.
  """
  name: str
  image: Path
  depth: Callable[[], np.ndarray] | None = None
  depth_file: str = ""
  panoptic: PanopticRef | None = None
  size: tuple[int, int] | None = None
  size_source: Path | None = None
  intrinsics: np.ndarray | None = None
  intrinsics_size: tuple[int, int] | None = None
  intrinsics_source: Path | None = None
  recording: str = ""

  def load(self) -> Frame:
    """Reads the frame; DataError when a file is unreadable or a size disagrees."""
    image = read_image(self.image)  # (H, W, 3)
    if self.size is not None and image.shape[:2] != tuple(self.size):
      raise DataError(self.image, f"image is {_wh(image.shape)} but {self.size_source} says "
                                  f"{_wh(self.size)} (W x H)")
    depth = None if self.depth is None else self.depth()
    panoptic, segments = None, ()
    if self.panoptic is not None:
      panoptic, segments = self.panoptic.load()
      if panoptic.shape != image.shape[:2]:
        raise DataError(self.panoptic.png, f"panoptic map is {_wh(panoptic.shape)} but its image "
                                           f"{self.image.name} is {_wh(image.shape)} (W x H)")
    return Frame(image=image, depth=depth, panoptic=panoptic, segments=segments, name=self.name,
                 intrinsics=self._intrinsics_for(image.shape[:2]), image_file=str(self.image),
                 depth_file=self.depth_file if depth is not None else "")

  def _intrinsics_for(self, size: tuple[int, int]) -> np.ndarray | None:
    """K of an image of `size` (H, W): `intrinsics` scaled from `intrinsics_size`."""
    if self.intrinsics is None or self.intrinsics_size is None or self.intrinsics_size == size:
      return self.intrinsics
    (h0, w0), (h, w) = self.intrinsics_size, size
    if abs(w / h - w0 / h0) > 0.01 * (w0 / h0):
      raise DataError(self.image, f"image is {_wh(size)} but the calibration "
                                  f"{self.intrinsics_source} is for {_wh(self.intrinsics_size)} "
                                  f"(W x H), another aspect ratio")
    from pitta_jax.data.resize import scale_intrinsics
    return scale_intrinsics(self.intrinsics, self.intrinsics_size, size)


@dataclasses.dataclass(frozen=True)
class _TransformedFiles(FrameFiles):
  """Files whose frame is transformed as it loads: the frames of a sequence joined to one with
  another transform (`FrameSequence.__add__`) keep their own."""
  post: Callable[[Frame], Frame] | None = None

  def load(self) -> Frame:
    frame = super().load()
    return frame if self.post is None else self.post(frame)


def _with_transform(files: FrameFiles, transform: Callable[[Frame], Frame] | None) -> FrameFiles:
  """`files` whose loaded frame is then given to `transform` (after a transform it has)."""
  if transform is None:
    return files
  fields = {f.name: getattr(files, f.name) for f in dataclasses.fields(FrameFiles)}
  first = getattr(files, "post", None)
  post = transform if first is None else (lambda frame: transform(first(frame)))
  return _TransformedFiles(**fields, post=post)


def _wh(shape: tuple[int, ...]) -> str:
  return f"{shape[1]}x{shape[0]}"


class FrameSequence(Sequence[Frame]):
  """Frames read on access.

  Args:
    files: the frames' files, in sequence order.
    transform: applied to each frame after loading (e.g. `functools.partial(resize_frame, ...)`).
    temporal: True when the order is capture order: consecutive frames of a recording (several
      recordings may follow each other), so frame i - 1 is the previous frame of frame i.
    remedies: for what the frames lack ("intrinsics", "previous_frame"), how the user supplies
      it (a flag or a file), one phrase each, used in error messages.
    notes: choices the reader made on its own that the user should see (one line each).
    evaluation: the dataset's evaluation protocol as `run.EvalConfig` values (field -> value)
      that its published results use, e.g. {"garg_crop": True} for KITTI's Eigen split; the CLI
      applies them where the user gives no flag.
    starts: per frame, whether it starts a recording; None: the first frame and where
      `FrameFiles.recording` changes. Joined sequences (`+`) start one at the join; a slice
      keeps its frames' values (a run resumed at frame k slices the sequence there).
  """

  def __init__(self, files: Sequence[FrameFiles],
               transform: Callable[[Frame], Frame] | None = None, *, temporal: bool = False,
               remedies: Mapping[str, str] | None = None, notes: Sequence[str] = (),
               evaluation: Mapping[str, object] | None = None,
               starts: Sequence[bool] | None = None):
    self.files = tuple(files)
    if starts is None:
      starts = [k == 0 or f.recording != self.files[k - 1].recording
                for k, f in enumerate(self.files)]
    if len(starts) != len(self.files):
      raise ValueError(f"starts has {len(starts)} values for {len(self.files)} frames")
    self.starts = tuple(bool(b) for b in starts)
    self.transform = transform
    self.temporal = temporal
    self.remedies = dict(remedies or {})
    self.notes = tuple(notes)
    self.evaluation = dict(evaluation or {})

  def _with(self, files: Sequence[FrameFiles], transform: Callable[[Frame], Frame] | None,
            starts: Sequence[bool], temporal: bool = True) -> FrameSequence:
    return FrameSequence(files, transform, temporal=self.temporal and temporal,
                         remedies=self.remedies, notes=self.notes, evaluation=self.evaluation,
                         starts=starts)

  def __len__(self) -> int:
    return len(self.files)

  @overload
  def __getitem__(self, index: int) -> Frame: ...

  @overload
  def __getitem__(self, index: slice) -> FrameSequence: ...

  def __getitem__(self, index: int | slice) -> Frame | FrameSequence:
    if isinstance(index, slice):
      # a stride skips frames (or reverses them): no longer consecutive
      return self._with(self.files[index], self.transform, self.starts[index],
                        temporal=index.step in (None, 1))
    frame = dataclasses.replace(self.files[index].load(), starts_recording=self.starts[index])
    return frame if self.transform is None else self.transform(frame)

  def __iter__(self) -> Iterator[Frame]:
    for k in range(len(self)):
      yield self[k]

  def check_files(self) -> None:
    """Every frame's image and panoptic PNG checked without decoding them
    (`image_io.check_image_file`: missing, empty, or a PNG cut short), so that a run finds such
    a file before any work rather than when it reaches the frame. DataError naming the first."""
    for f in self.files:
      check_image_file(f.image, "image")
      if f.panoptic is not None:
        check_image_file(f.panoptic.png, "panoptic PNG")

  @property
  def names(self) -> tuple[str, ...]:
    """The frames' names, without loading them."""
    return tuple(f.name for f in self.files)

  def map(self, transform: Callable[[Frame], Frame]) -> FrameSequence:
    """The same frames with `transform` applied (after any existing transform) on access."""
    if self.transform is None:
      return self._with(self.files, transform, self.starts)
    first = self.transform
    return self._with(self.files, lambda frame: transform(first(frame)), self.starts)

  def __add__(self, other: FrameSequence) -> FrameSequence:
    """The frames of `other` after these, still read on access; other's first frame starts a
    recording. Sequences with different transforms (e.g. two readers' resizes) each keep their
    own."""
    if not isinstance(other, FrameSequence):
      return NotImplemented
    if other.evaluation != self.evaluation:
      raise ValueError(f"cannot join frames evaluated differently: {self.evaluation} and "
                       f"{other.evaluation}")
    files, transform = self.files + other.files, self.transform
    if other.transform is not self.transform:
      files = tuple(_with_transform(f, self.transform) for f in self.files) + tuple(
          _with_transform(f, other.transform) for f in other.files)
      transform = None
    return FrameSequence(files, transform,
                         temporal=self.temporal and other.temporal,
                         remedies={**other.remedies, **self.remedies},
                         notes=self.notes + tuple(n for n in other.notes if n not in self.notes),
                         evaluation=self.evaluation,
                         starts=self.starts + tuple(k == 0 or b
                                                    for k, b in enumerate(other.starts)))

  def __repr__(self) -> str:
    first = f", first={self.files[0].name!r}" if self.files else ""
    return f"FrameSequence(len={len(self)}{first})"


class JoinedFrames(Sequence[Frame]):
  """Sequences of frames one after another, read on access (e.g. the rendered parts of a
  synthetic test case: `FrameSequence`s join with `+`). The first frame of each part starts a
  recording (a method never pairs frames of two parts); a slice keeps its frames' marks.

  Args:
    parts: the sequences (any `Sequence[Frame]`), in order.
    starts: per part, whether its first frame starts a recording (default: all).
  """

  def __init__(self, parts: Sequence[Sequence[Frame]], starts: Sequence[bool] | None = None):
    self.parts = tuple(parts)
    self.starts = tuple(starts) if starts is not None else (True,) * len(self.parts)
    self._ends = tuple(np.cumsum([len(p) for p in self.parts], dtype=np.int64).tolist())

  def __len__(self) -> int:
    return self._ends[-1] if self._ends else 0

  @overload
  def __getitem__(self, index: int) -> Frame: ...

  @overload
  def __getitem__(self, index: slice) -> JoinedFrames: ...

  def __getitem__(self, index: int | slice) -> Frame | JoinedFrames:
    if isinstance(index, slice):
      start, stop, step = index.indices(len(self))
      if step != 1:
        return JoinedFrames([[self[i] for i in range(start, stop, step)]], (False,))
      parts, starts, begin = [], [], 0
      for part, first, end in zip(self.parts, self.starts, self._ends):
        lo, hi = max(start - begin, 0), min(stop, end) - begin
        if hi > lo:
          parts.append(part[lo:hi])
          starts.append(first and lo == 0)
        begin = end
      return JoinedFrames(parts, starts)
    i = index.__index__()
    if not -len(self) <= i < len(self):
      raise IndexError(f"frame {index} of a sequence of {len(self)}")
    i %= len(self)
    k = int(np.searchsorted(self._ends, i, side="right"))
    j = i - (self._ends[k - 1] if k else 0)
    frame = self.parts[k][j]
    return dataclasses.replace(frame, starts_recording=True) if j == 0 and self.starts[k] \
        else frame

  def __iter__(self) -> Iterator[Frame]:
    for k in range(len(self)):
      yield self[k]

  @property
  def names(self) -> tuple[str, ...]:
    """The frames' names, without reading them where the parts can tell them so."""
    return tuple(name for part in self.parts for name in (
        getattr(part, "names", None) or [frame.name for frame in part]))

  def __repr__(self) -> str:
    return f"JoinedFrames(len={len(self)}, parts={len(self.parts)})"


def require_frames(files: Sequence[FrameFiles], searched: Path | str, pattern: str
                   ) -> Sequence[FrameFiles]:
  """`files`, or DataError naming the directory searched and the pattern when there are none."""
  if not files:
    raise DataError(searched, f"no frames found (looked for {pattern})")
  return files
