"""COCO panoptic files: the RGB-encoded id PNG and its `segments_info` JSON.

Format (panopticapi, see docs/datasets.md): an RGB PNG whose pixel value encodes the
segment id as `id = R + 256 G + 256^2 B` (0 = void), and per image a list `segments_info` of
`{"id", "category_id", "iscrowd", "bbox": [x, y, w, h], "area"}` (optionally `"isthing"`),
`category_id` being a COCO category id (`pitta_jax.data.coco`). Two JSON layouts are read:

- per image: `<stem>.json` beside `<stem>.png`, holding `{"segments_info": [...]}` (what our
  synthetic exporter and `write_panoptic` write);
- COCO style: one annotation file `{"annotations": [{"file_name", "segments_info"}, ...],
  "categories": [{"id", "isthing", ...}, ...]}` whose PNGs lie in one directory (by COCO
  convention the JSON path without `.json`, e.g. `panoptic_val2017.json` + `panoptic_val2017/`).
  Without an explicit file, one annotation file inside the PNG directory or beside it as
  `<directory>.json` is found on its own (`find_annotation_file`).

`isthing` comes from the segment entry, else from the file's `categories`, else from the COCO
table. An annotation file whose `categories` name its ids otherwise than COCO does (another
taxonomy, e.g. cityscapesScripts' `createPanopticImgs.py`, where 24 is "person" and 26 "car",
COCO's "zebra" and no class) has its ids mapped to COCO's by name (`coco_ids_by_name`), with a
note; a category COCO does not name keeps its id where COCO has no such id, else gets 0 (no
COCO class: never dynamic). Elsewhere a `category_id` that is not a COCO panoptic id is an
error, as in panopticapi's checks (Detectron2's contiguous class numbers are not COCO ids).
Segments listed in the JSON but absent from the PNG are dropped (a
`Frame` holds the segments present in its map); ids in the PNG without a JSON entry are an
error, as in panopticapi's own checks.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path, PurePosixPath
from typing import Any, Mapping, Sequence

import numpy as np

from pitta_jax.data import coco
from pitta_jax.data.errors import DataError
from pitta_jax.data.frame import Segment
from pitta_jax.data.image_io import (PathLike, decode_file, encode_bytes, encode_file,
                                     require_dir, require_file)
from pitta_jax.text import first_and_count

MAX_ID = 256**3 - 1  # the largest id an RGB PNG can encode


def rgb_to_id(rgb: np.ndarray) -> np.ndarray:
  """(H, W, 3) uint8 RGB -> (H, W) int32 ids, `R + 256 G + 256^2 B`."""
  rgb = np.asarray(rgb).astype(np.int32)
  return rgb[..., 0] + 256 * rgb[..., 1] + 256 * 256 * rgb[..., 2]


def id_to_rgb(ids: np.ndarray) -> np.ndarray:
  """(H, W) ids in 0..2^24-1 -> (H, W, 3) uint8 RGB, the inverse of `rgb_to_id`."""
  ids = np.asarray(ids).astype(np.int64)
  if ids.size and (ids.min() < 0 or ids.max() > MAX_ID):
    raise ValueError(f"panoptic ids must lie in 0..{MAX_ID}, got {ids.min()}..{ids.max()}")
  return np.stack([ids % 256, ids // 256 % 256, ids // 65536], axis=-1).astype(np.uint8)


def read_panoptic_png(path: PathLike) -> np.ndarray:
  """Reads a COCO panoptic PNG; (H, W) int32 segment ids, 0 = void."""
  array = decode_file(require_file(path, "panoptic PNG"), "panoptic PNG")
  if array.ndim != 3 or array.shape[2] not in (3, 4) or array.dtype != np.uint8:
    channels = 1 if array.ndim == 2 else array.shape[2]
    raise DataError(path, f"panoptic PNG must be 8-bit RGB (id = R + 256 G + 256^2 B), got "
                          f"{array.dtype} with {channels} channel(s)")
  return rgb_to_id(array[..., 2::-1])  # BGR(A) on disk -> RGB


def write_panoptic_png(path: PathLike, ids: np.ndarray) -> None:
  """Writes (H, W) integer ids as a COCO panoptic RGB PNG."""
  encode_file(path, id_to_rgb(ids)[..., ::-1], "panoptic PNG")


def is_segments_json(path: Path) -> bool:
  """Whether `path` is a per-image panoptic JSON as `write_panoptic` writes it, `{"segments_info":
  [...]}` and nothing else (not, e.g., a labelme annotation of the same stem)."""
  try:
    data = json.loads(Path(path).read_text())
  except (OSError, ValueError):
    return False
  return isinstance(data, dict) and set(data) == {"segments_info"}


def segments_info(ids: np.ndarray, segments: Sequence[Segment]) -> list[dict[str, Any]]:
  """COCO `segments_info` entries of `segments` in the id map `ids` (H, W).

  `bbox` is `[x, y, w, h]` of the segment's pixels and `area` their count (both 0 for a
  segment absent from the map); `iscrowd` is 0 and `isthing` is written too.
  """
  ids = np.asarray(ids)
  entries = []
  for seg in segments:
    rows, cols = np.nonzero(ids == seg.id)
    if rows.size:
      bbox = [int(cols.min()), int(rows.min()), int(cols.max() - cols.min() + 1),
              int(rows.max() - rows.min() + 1)]
    else:
      bbox = [0, 0, 0, 0]
    entries.append({"id": int(seg.id), "category_id": int(seg.category_id), "iscrowd": 0,
                    "bbox": bbox, "area": int(rows.size), "isthing": bool(seg.isthing)})
  return entries


def write_panoptic(png_path: PathLike, ids: np.ndarray, segments: Sequence[Segment]) -> Path:
  """Writes `<stem>.png` and the per-image `<stem>.json` beside it; returns the JSON path.

  Both at once (`outputs.atomic_write_files`: both written, then renamed, the JSON first): an
  interrupted run leaves an image with both files or neither, never a PNG without its
  segments (readers pair by PNG) nor a JSON without its PNG (`segment` would refuse to rerun)."""
  from pitta_jax.outputs import atomic_write_files
  png_path = Path(png_path)
  json_path = png_path.with_suffix(".json")
  png = encode_bytes(png_path, id_to_rgb(ids)[..., ::-1], "panoptic PNG")
  try:
    png_path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_files(png_path.parent, {
        json_path.name: json.dumps({"segments_info": segments_info(ids, segments)}),
        png_path.name: png})
  except OSError as e:
    raise DataError(png_path, f"cannot write the panoptic PNG and its JSON "
                              f"({e.strerror or e})") from None
  return json_path


def _read_json(path: PathLike) -> Any:
  path = require_file(path, "panoptic JSON")
  try:
    return json.loads(path.read_text())
  except (json.JSONDecodeError, UnicodeDecodeError) as e:
    raise DataError(path, f"invalid JSON ({e})") from None


def parse_segments(entries: Any, path: PathLike, categories: Mapping[int, bool] | None = None
                   ) -> tuple[Segment, ...]:
  """`segments_info` entries -> Segments.

  Args:
    entries: the JSON list of segment dicts.
    path: the file they came from (for error messages).
    categories: COCO id -> isthing from the file's `categories`, if it has them.
  """
  if not isinstance(entries, list):
    raise DataError(path, "'segments_info' must be a list")
  segments = []
  seen = set()
  for k, entry in enumerate(entries):
    if not isinstance(entry, dict) or "id" not in entry or "category_id" not in entry:
      raise DataError(path, f"segments_info[{k}] lacks 'id' or 'category_id'")
    seg_id, category_id = entry["id"], entry["category_id"]
    if (not isinstance(seg_id, int) or isinstance(seg_id, bool) or not 0 < seg_id <= MAX_ID
        or not isinstance(category_id, int) or isinstance(category_id, bool)):
      raise DataError(path, f"segments_info[{k}] has invalid id {seg_id!r} or category_id "
                            f"{category_id!r}")
    if seg_id in seen:
      raise DataError(path, f"segment id {seg_id} listed twice in segments_info")
    seen.add(seg_id)
    if categories is None or category_id not in categories:  # read as a COCO id
      _check_coco_id(category_id, path, k)
    if "isthing" in entry:
      isthing = bool(entry["isthing"])
    elif categories is not None and category_id in categories:
      isthing = categories[category_id]
    else:
      isthing = coco.is_thing(category_id)
    segments.append(Segment(id=seg_id, category_id=category_id, isthing=isthing))
  return tuple(segments)


CONTIGUOUS_HINT = ("Detectron2 and Mask2Former number the classes 0-132 in their own order: "
                   "give COCO's ids, e.g. 1 person, 3 car")


def _check_coco_id(category_id: int, path: PathLike, k: int) -> None:
  """A category id read as COCO's must be one (as panopticapi checks), 'isthing' given or not:
  a class numbering of another kind (Detectron2's contiguous 0-132: its 0 is COCO's person)
  would leave dynamic segments out of the mask, silently."""
  if category_id not in coco.CATEGORY_IDS:
    raise DataError(path, f"segments_info[{k}]: category_id {category_id} is not a COCO panoptic "
                          f"category id ({CONTIGUOUS_HINT})")


def read_segments_json(path: PathLike) -> tuple[Segment, ...]:
  """Reads a per-image JSON `{"segments_info": [...]}` (a bare list is accepted too)."""
  data = _read_json(path)
  if isinstance(data, dict):
    if "segments_info" not in data:
      raise DataError(path, "no 'segments_info' key (a COCO annotation file? pass it as the "
                            "panoptic annotation file instead)")
    data = data["segments_info"]
  return parse_segments(data, path)


def _key(file_name: str) -> str:
  """Lookup key of an annotation's file name: the relative path without suffix."""
  return str(PurePosixPath(file_name).with_suffix(""))


# names of other taxonomies whose class COCO files under another name (COCO labels a rider as
# a person; Cityscapes' "rider" is the person on a bicycle or motorcycle)
COCO_NAME_ALIASES = {"rider": "person"}


def coco_ids_by_name(categories: Sequence[Any], path: PathLike
                     ) -> tuple[dict[int, int], str | None]:
  """The COCO id of each of a file's categories ({"id", "name", ...} entries), by name, and a
  note when that is not the identity (None when every id already means COCO's class).

  A category named as a COCO one (case and `-`/`_` ignored, `COCO_NAME_ALIASES`) gets its COCO
  id; one COCO does not name keeps its id if COCO has no such id, else gets 0 (no COCO class).
  """
  def norm(name: str) -> str:
    return name.strip().lower().replace("_", " ").replace("-", " ")
  coco_names = {norm(c.name): c for c in coco.CATEGORIES}
  mapping, renamed, unknown = {}, [], []
  for c in categories:
    if not isinstance(c, dict) or not isinstance(c.get("id"), int) or \
        not isinstance(c.get("name"), str):
      continue
    name = norm(c["name"])
    target = coco_names.get(norm(COCO_NAME_ALIASES.get(name, name)))
    if target is not None:
      mapping[c["id"]] = target.id
      if target.id != c["id"]:
        renamed.append(f"{c['id']} {c['name']!r} -> {target.id}")
    elif c["id"] in coco.CATEGORY_IDS:
      mapping[c["id"]] = 0
      unknown.append(f"{c['id']} {c['name']!r}")
  if not renamed and not unknown:
    return mapping, None

  def first(items: list[str], n: int = 8) -> str:
    return ", ".join(items[:n]) + (", ..." if len(items) > n else "")
  note = f"{path}: category ids are not COCO's; mapped by name to COCO ids ({first(renamed)})"
  if unknown:
    note += f"; without a COCO class (id 0, never dynamic): {first(unknown)}"
  return mapping, note


def read_annotation_file(path: PathLike) -> tuple[dict[str, tuple[Segment, ...]], tuple[str, ...]]:
  """Reads a COCO-style panoptic annotation file.

  Returns:
    segments by key, the key being each annotation's `file_name` without its suffix
    (`"000000000139.png"` -> `"000000000139"`), with COCO category ids (`coco_ids_by_name`);
    and the notes on what was mapped.
  """
  data = _read_json(path)
  if not isinstance(data, dict) or not isinstance(data.get("annotations"), list):
    raise DataError(path, "not a COCO panoptic annotation file (no 'annotations' list)")
  categories, mapping, notes = None, {}, ()
  if isinstance(data.get("categories"), list):
    # (an id that is not an int, e.g. a list, is no segment's category_id: left out)
    categories = {c["id"]: bool(c["isthing"]) for c in data["categories"]
                  if isinstance(c, dict) and isinstance(c.get("id"), int) and "isthing" in c}
    mapping, note = coco_ids_by_name(data["categories"], path)
    notes = (note,) if note else ()
  table = {}
  for k, ann in enumerate(data["annotations"]):
    if not isinstance(ann, dict) or "file_name" not in ann or "segments_info" not in ann:
      raise DataError(path, f"annotations[{k}] lacks 'file_name' or 'segments_info'")
    if not isinstance(ann["file_name"], str):  # (the key of its PNG; a number is no file name)
      raise DataError(path, f"annotations[{k}] has file_name {ann['file_name']!r}, expected "
                            f"the PNG's name, e.g. '000000000139.png'")
    segments = parse_segments(ann["segments_info"], path, categories)
    table[_key(ann["file_name"])] = tuple(
        dataclasses.replace(s, category_id=mapping.get(s.category_id, s.category_id))
        for s in segments)
  return table, notes


def check_segments(ids: np.ndarray, segments: Sequence[Segment], path: PathLike
                   ) -> tuple[Segment, ...]:
  """Segments present in `ids`; DataError when the map holds ids without a segment entry."""
  present = set(np.unique(ids).tolist()) - {0}
  listed = {s.id for s in segments}
  unlisted = sorted(present - listed)
  if unlisted:
    raise DataError(path, f"segment ids {first_and_count(unlisted, 5)} appear in the PNG but not in segments_info")
  return tuple(s for s in segments if s.id in present)


@dataclasses.dataclass(frozen=True)
class PanopticRef:
  """Where one frame's panoptic segmentation lives; `load()` reads it.

  png: the id PNG.
  json: the per-image JSON (None when `segments` came from an annotation file).
  segments: the segments from an annotation file (None when read from `json`).
  """
  png: Path
  json: Path | None = None
  segments: tuple[Segment, ...] | None = None

  def load(self) -> tuple[np.ndarray, tuple[Segment, ...]]:
    """(H, W) int32 ids and the segments present in them."""
    ids = read_panoptic_png(self.png)
    segments = self.segments if self.json is None else read_segments_json(self.json)
    return ids, check_segments(ids, segments or (), self.png)


def is_annotation_file(path: Path) -> bool:
  """True when `path` is JSON holding a COCO panoptic `annotations` list."""
  data = _read_json(path)
  return isinstance(data, dict) and isinstance(data.get("annotations"), list)


def find_annotation_file(directory: Path) -> Path | None:
  """The one COCO annotation file of a PNG directory, or None (per-image JSONs).

  Candidates: the JSON files inside `directory` without a PNG of the same stem (a per-image
  JSON has one) and `<directory>.json` beside it (COCO's convention); only those holding an
  `annotations` list count. More than one is an error (which one is meant is unknown).
  """
  inside = [p for p in sorted(directory.glob("*.json")) if not p.name.startswith(".")
            and p.is_file() and not p.with_suffix(".png").is_file()]
  beside = directory.parent / f"{directory.name}.json"
  found = [p for p in inside + ([beside] if beside.is_file() else []) if is_annotation_file(p)]
  if len(found) > 1:
    names = ", ".join(p.name for p in found)
    raise DataError(directory, f"several COCO annotation files ({names}); pass one with "
                               f"--option panoptic_json=FILE")
  return found[0] if found else None


class PanopticSource:
  """A directory of panoptic PNGs with per-image JSONs or one COCO annotation file.

  Args:
    directory: the PNG directory; None with `annotation_file` = the annotation file's path
      without `.json` (COCO convention).
    annotation_file: a COCO-style annotation JSON; None = the one annotation file found inside
      or beside `directory` (`find_annotation_file`), if any, else per-image `<key>.json` files.
      A frame without an annotation but with its own `<key>.json` is read from that.

  `notes` says which annotation file was found (the user did not name it).
  """

  def __init__(self, directory: PathLike | None = None, annotation_file: PathLike | None = None):
    if directory is None and annotation_file is None:
      raise ValueError("PanopticSource needs a directory or an annotation file")
    if directory is None:
      directory = Path(annotation_file).with_suffix("")
    self.directory = require_dir(directory, "panoptic directory")
    self.notes: tuple[str, ...] = ()
    if annotation_file is None:
      annotation_file = find_annotation_file(self.directory)
      if annotation_file is not None:
        self.notes = (f"panoptic segments from the COCO annotation file {annotation_file}",)
    self.annotation_file = None if annotation_file is None else Path(annotation_file)
    self._table = None
    if annotation_file is not None:
      self._table, mapped = read_annotation_file(annotation_file)
      self.notes += mapped

  def _file_names_hint(self) -> str:
    """For a frame not found: what the annotation file's file_names look like."""
    example = next(iter(self._table or ()), None)
    return (f" (the file_names in {self.annotation_file.name} are like '{example}.png')"
            if example is not None else "")

  def has(self, key: str) -> bool:
    """True when frame `key` has a PNG and its segments (an annotation or its own JSON)."""
    png = self.directory / f"{key}.png"
    if not png.is_file():
      return False
    return (self._table is not None and key in self._table) or png.with_suffix(".json").is_file()

  def ref(self, key: str) -> PanopticRef:
    """The panoptic files of frame `key` (a relative path without suffix, e.g. a file stem).

    Raises DataError when the PNG, its JSON or its annotation is missing.
    """
    png = self.directory / f"{key}.png"
    if not png.is_file() and self._table is not None and key not in self._table:
      raise DataError(png, f"panoptic PNG not found{self._file_names_hint()}")
    png = require_file(png, "panoptic PNG")
    if self._table is not None and key in self._table:
      return PanopticRef(png=png, segments=self._table[key])
    if png.with_suffix(".json").is_file():
      return PanopticRef(png=png, json=png.with_suffix(".json"))
    if self._table is not None:
      raise DataError(self.annotation_file, f"no annotation with file_name '{key}.png' (nor a "
                                            f"per-image {png.with_suffix('.json').name})"
                                            f"{self._file_names_hint()}")
    raise DataError(png.with_suffix(".json"), "panoptic JSON not found (per-image JSON, or one "
                                              "COCO annotation file in the PNG directory or "
                                              "beside it as <directory>.json, or --option "
                                              "panoptic_json=FILE)")


def panoptic_source(directory: PathLike | None, annotation_file: PathLike | None
                    ) -> PanopticSource | None:
  """`PanopticSource(directory, annotation_file)`, or None when both are None."""
  if directory is None and annotation_file is None:
    return None
  return PanopticSource(directory, annotation_file)
