"""Frames of the synthetic benchmark: street layout -> clear render -> weather -> `Frame`."""

from __future__ import annotations

import dataclasses
from typing import Iterator, Sequence, overload

import numpy as np

from pitta_jax.data.frame import Frame
from pitta_jax.data.synthetic import config as C
from pitta_jax.data.synthetic.render import Render, render
from pitta_jax.data.synthetic.scene import Street
from pitta_jax.data.synthetic.weather import apply_weather


def frame_name(domain: str, seed: int, index: int) -> str:
  return f"{domain}/{seed}/{index:06d}"


def ground_truth_depth(r: Render, max_depth: float) -> np.ndarray:
  """(H, W) float32 metres: the z-depth where a surface was hit within max_depth, else 0."""
  return np.where(r.dist <= max_depth, r.dist, np.float32(0.0)).astype(np.float32)


def _frame(cfg: C.SyntheticConfig, r: Render, domain: str, severity: float, index: int) -> Frame:
  fx, fy, cx, cy = C.intrinsics(cfg.height, cfg.width)
  K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
  return Frame(image=apply_weather(r, domain, severity, cfg.seed, index),
               depth=ground_truth_depth(r, cfg.max_depth), panoptic=r.panoptic,
               segments=r.segments, name=frame_name(domain, cfg.seed, index), intrinsics=K)


def render_clear(cfg: C.SyntheticConfig, index: int, street: Street | None = None) -> Render:
  """The clear-weather render of frame `index`.

  street: optional `Street(cfg')` to reuse its block caches, with cfg' equal to cfg in the
  seed, size-independent layout and traffic fields (the domain may differ).
  """
  street = street or Street(cfg)
  return render(street, street.frame(index), cfg.height, cfg.width)


def render_frame(cfg: C.SyntheticConfig, index: int, street: Street | None = None) -> Frame:
  """Frame `index` of the sequence `cfg` in `cfg.domain` (random access; equal to the same
  frame of `generate_sequence`)."""
  return _frame(cfg, render_clear(cfg, index, street), cfg.domain, cfg.severity, index)


def iter_frames(cfg: C.SyntheticConfig) -> Iterator[Frame]:
  """Frames cfg.start .. cfg.start + cfg.num_frames - 1, in order."""
  street = Street(cfg)
  for index in range(cfg.start, cfg.start + cfg.num_frames):
    yield render_frame(cfg, index, street)


def generate_sequence(cfg: C.SyntheticConfig) -> list[Frame]:
  """All frames of `cfg` (see `iter_frames` to stream long sequences)."""
  return list(iter_frames(cfg))


class SyntheticSequence(Sequence[Frame]):
  """The frames of `cfg`, each rendered when it is read (random access, equal to
  `generate_sequence(cfg)`'s): a run over a long synthetic sequence streams it as it streams a
  dataset's files, where rendering every frame first held them all in memory and sat silent
  (3 million frames: ~2 TB) before the first step. One `Street` serves every read (its block
  caches)."""

  def __init__(self, cfg: C.SyntheticConfig, street: Street | None = None):
    self.cfg = cfg
    self._street = street

  def __len__(self) -> int:
    return self.cfg.num_frames

  @overload
  def __getitem__(self, index: int) -> Frame: ...

  @overload
  def __getitem__(self, index: slice) -> "SyntheticSequence": ...

  def __getitem__(self, index):
    if isinstance(index, slice):
      start, stop, step = index.indices(len(self))
      if step != 1:
        return [self[i] for i in range(start, stop, step)]
      return SyntheticSequence(dataclasses.replace(self.cfg, start=self.cfg.start + start,
                                                   num_frames=max(stop - start, 0)),
                               self._street)
    i = index.__index__()
    if not -len(self) <= i < len(self):
      raise IndexError(f"frame {index} of a sequence of {len(self)}")
    if self._street is None:
      self._street = Street(self.cfg)
    return render_frame(self.cfg, self.cfg.start + i % len(self), self._street)

  @property
  def names(self) -> tuple[str, ...]:
    """The frames' names, without rendering them."""
    return tuple(frame_name(self.cfg.domain, self.cfg.seed, self.cfg.start + i)
                 for i in range(len(self)))


def iter_domains(cfg: C.SyntheticConfig,
                 domains: Sequence[str] = C.DOMAINS) -> Iterator[dict[str, Frame]]:
  """Per index, the frame in each of `domains` (one render, several weathers): the same
  geometry, depth and panoptic arrays in every domain."""
  street = Street(cfg)
  for index in range(cfg.start, cfg.start + cfg.num_frames):
    r = render_clear(cfg, index, street)
    yield {d: _frame(cfg, r, d, cfg.severity, index) for d in domains}
