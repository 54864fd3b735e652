"""The 133 COCO panoptic categories, in detectron2's contiguous order.

Facts from panopticapi's `panoptic_coco_categories.json` as ordered by detectron2's
`COCO_CATEGORIES` (`detectron2/data/datasets/builtin_meta.py`): the 80 things first, then the
53 stuff classes. A Mask2Former trained with detectron2's `coco_panoptic_standard` metadata
predicts the *contiguous* index (0..132, the position in this table); COCO panoptic JSON files
and `pitta_jax.data.frame.Segment` carry the COCO *category id* (1..200, with gaps).

The dynamic set O of the paper (Sec. 3.1) is `DYNAMIC_NAMES`: COCO ids 1, 2, 3, 4, 6, 7, 8,
contiguous 0, 1, 2, 3, 5, 6, 7. COCO has no `rider` class.
"""

from __future__ import annotations

from typing import Iterable, NamedTuple

import numpy as np


class Category(NamedTuple):
  """One COCO panoptic category.

  id: COCO category id (as in panoptic JSON files).
  name: COCO name ("person", "traffic light", "sky-other-merged", ...).
  isthing: True for countable objects (instances), False for stuff.
  contiguous: detectron2's contiguous index 0..132 (things 0..79, stuff 80..132).
  """
  id: int
  name: str
  isthing: bool
  contiguous: int


CATEGORIES: tuple[Category, ...] = (
    Category(1, "person", True, 0),
    Category(2, "bicycle", True, 1),
    Category(3, "car", True, 2),
    Category(4, "motorcycle", True, 3),
    Category(5, "airplane", True, 4),
    Category(6, "bus", True, 5),
    Category(7, "train", True, 6),
    Category(8, "truck", True, 7),
    Category(9, "boat", True, 8),
    Category(10, "traffic light", True, 9),
    Category(11, "fire hydrant", True, 10),
    Category(13, "stop sign", True, 11),
    Category(14, "parking meter", True, 12),
    Category(15, "bench", True, 13),
    Category(16, "bird", True, 14),
    Category(17, "cat", True, 15),
    Category(18, "dog", True, 16),
    Category(19, "horse", True, 17),
    Category(20, "sheep", True, 18),
    Category(21, "cow", True, 19),
    Category(22, "elephant", True, 20),
    Category(23, "bear", True, 21),
    Category(24, "zebra", True, 22),
    Category(25, "giraffe", True, 23),
    Category(27, "backpack", True, 24),
    Category(28, "umbrella", True, 25),
    Category(31, "handbag", True, 26),
    Category(32, "tie", True, 27),
    Category(33, "suitcase", True, 28),
    Category(34, "frisbee", True, 29),
    Category(35, "skis", True, 30),
    Category(36, "snowboard", True, 31),
    Category(37, "sports ball", True, 32),
    Category(38, "kite", True, 33),
    Category(39, "baseball bat", True, 34),
    Category(40, "baseball glove", True, 35),
    Category(41, "skateboard", True, 36),
    Category(42, "surfboard", True, 37),
    Category(43, "tennis racket", True, 38),
    Category(44, "bottle", True, 39),
    Category(46, "wine glass", True, 40),
    Category(47, "cup", True, 41),
    Category(48, "fork", True, 42),
    Category(49, "knife", True, 43),
    Category(50, "spoon", True, 44),
    Category(51, "bowl", True, 45),
    Category(52, "banana", True, 46),
    Category(53, "apple", True, 47),
    Category(54, "sandwich", True, 48),
    Category(55, "orange", True, 49),
    Category(56, "broccoli", True, 50),
    Category(57, "carrot", True, 51),
    Category(58, "hot dog", True, 52),
    Category(59, "pizza", True, 53),
    Category(60, "donut", True, 54),
    Category(61, "cake", True, 55),
    Category(62, "chair", True, 56),
    Category(63, "couch", True, 57),
    Category(64, "potted plant", True, 58),
    Category(65, "bed", True, 59),
    Category(67, "dining table", True, 60),
    Category(70, "toilet", True, 61),
    Category(72, "tv", True, 62),
    Category(73, "laptop", True, 63),
    Category(74, "mouse", True, 64),
    Category(75, "remote", True, 65),
    Category(76, "keyboard", True, 66),
    Category(77, "cell phone", True, 67),
    Category(78, "microwave", True, 68),
    Category(79, "oven", True, 69),
    Category(80, "toaster", True, 70),
    Category(81, "sink", True, 71),
    Category(82, "refrigerator", True, 72),
    Category(84, "book", True, 73),
    Category(85, "clock", True, 74),
    Category(86, "vase", True, 75),
    Category(87, "scissors", True, 76),
    Category(88, "teddy bear", True, 77),
    Category(89, "hair drier", True, 78),
    Category(90, "toothbrush", True, 79),
    Category(92, "banner", False, 80),
    Category(93, "blanket", False, 81),
    Category(95, "bridge", False, 82),
    Category(100, "cardboard", False, 83),
    Category(107, "counter", False, 84),
    Category(109, "curtain", False, 85),
    Category(112, "door-stuff", False, 86),
    Category(118, "floor-wood", False, 87),
    Category(119, "flower", False, 88),
    Category(122, "fruit", False, 89),
    Category(125, "gravel", False, 90),
    Category(128, "house", False, 91),
    Category(130, "light", False, 92),
    Category(133, "mirror-stuff", False, 93),
    Category(138, "net", False, 94),
    Category(141, "pillow", False, 95),
    Category(144, "platform", False, 96),
    Category(145, "playingfield", False, 97),
    Category(147, "railroad", False, 98),
    Category(148, "river", False, 99),
    Category(149, "road", False, 100),
    Category(151, "roof", False, 101),
    Category(154, "sand", False, 102),
    Category(155, "sea", False, 103),
    Category(156, "shelf", False, 104),
    Category(159, "snow", False, 105),
    Category(161, "stairs", False, 106),
    Category(166, "tent", False, 107),
    Category(168, "towel", False, 108),
    Category(171, "wall-brick", False, 109),
    Category(175, "wall-stone", False, 110),
    Category(176, "wall-tile", False, 111),
    Category(177, "wall-wood", False, 112),
    Category(178, "water-other", False, 113),
    Category(180, "window-blind", False, 114),
    Category(181, "window-other", False, 115),
    Category(184, "tree-merged", False, 116),
    Category(185, "fence-merged", False, 117),
    Category(186, "ceiling-merged", False, 118),
    Category(187, "sky-other-merged", False, 119),
    Category(188, "cabinet-merged", False, 120),
    Category(189, "table-merged", False, 121),
    Category(190, "floor-other-merged", False, 122),
    Category(191, "pavement-merged", False, 123),
    Category(192, "mountain-merged", False, 124),
    Category(193, "grass-merged", False, 125),
    Category(194, "dirt-merged", False, 126),
    Category(195, "paper-merged", False, 127),
    Category(196, "food-other-merged", False, 128),
    Category(197, "building-other-merged", False, 129),
    Category(198, "rock-merged", False, 130),
    Category(199, "wall-other-merged", False, 131),
    Category(200, "rug-merged", False, 132),
)

NUM_CLASSES = len(CATEGORIES)  # 133
NUM_THINGS = sum(c.isthing for c in CATEGORIES)  # 80

# The paper's dynamic object classes O (Sec. 3.1): vehicles and people.
DYNAMIC_NAMES: tuple[str, ...] = ("person", "bicycle", "car", "motorcycle", "bus", "train", "truck")

_BY_ID: dict[int, Category] = {c.id: c for c in CATEGORIES}
CATEGORY_IDS = frozenset(_BY_ID)  # the 133 ids of COCO panoptic
_BY_NAME: dict[str, Category] = {c.name: c for c in CATEGORIES}


def by_id(category_id: int) -> Category:
  """The category with COCO id `category_id`; KeyError if COCO panoptic has none."""
  try:
    return _BY_ID[int(category_id)]
  except KeyError:
    raise KeyError(f"no COCO panoptic category with id {category_id}") from None


def by_name(name: str) -> Category:
  """The category called `name` (exact COCO spelling); KeyError naming close matches."""
  try:
    return _BY_NAME[name]
  except KeyError:
    close = [n for n in _BY_NAME if name.lower() in n or n in name.lower()]
    hint = f" (did you mean {', '.join(close)}?)" if close else ""
    raise KeyError(f"no COCO panoptic category named {name!r}{hint}") from None


def name_to_id(name: str) -> int:
  """COCO category id of `name`, e.g. "car" -> 3."""
  return by_name(name).id


def id_to_contiguous(category_id: int) -> int:
  """detectron2 contiguous index of a COCO category id, e.g. 3 (car) -> 2."""
  return by_id(category_id).contiguous


def contiguous_to_id(index: int) -> int:
  """COCO category id of a detectron2 contiguous index, e.g. 2 -> 3 (car)."""
  if not 0 <= index < NUM_CLASSES:
    raise KeyError(f"contiguous index {index} outside 0..{NUM_CLASSES - 1}")
  return CATEGORIES[index].id


def is_thing(category_id: int) -> bool:
  """True when the COCO category id is a thing class."""
  return by_id(category_id).isthing


def ids_of(names: Iterable[str]) -> tuple[int, ...]:
  """COCO ids of `names` in order; `ids_of(DYNAMIC_NAMES)` = (1, 2, 3, 4, 6, 7, 8)."""
  return tuple(name_to_id(n) for n in names)


def contiguous_to_id_table() -> np.ndarray:
  """(133,) int32: entry k is the COCO id of contiguous index k (for vectorised mapping)."""
  return np.array([c.id for c in CATEGORIES], np.int32)


def is_thing_table() -> np.ndarray:
  """(133,) bool: entry k is True when contiguous index k is a thing class."""
  return np.array([c.isthing for c in CATEGORIES], bool)
