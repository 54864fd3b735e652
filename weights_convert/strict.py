"""Strict loading: a checkpoint's keys must be exactly the ones a converter's key table uses."""

from __future__ import annotations

from typing import Callable, Iterable, Sequence

from pitta_jax.text import first_and_count
from weights_convert.pth import CheckpointError


SHOWN_KEYS = 8  # keys named per kind in a message; the rest are counted

# key prefixes of the upstream checkpoints -> what the file is and its converter: named when a
# file holds another network's keys (first match wins)
LAYOUTS = (
    ("common.encoder.encoder.", "SGDepth's model.pth (`pitta-jax convert sgdepth`)"),
    ("pretrained.cls_token", "an official Depth Anything V2 .pth (`pitta-jax convert "
                             "depth-anything-v2`)"),
    ("backbone.embeddings.", "Hugging Face Depth Anything V2 weights (`pitta-jax convert "
                             "depth-anything-v2 --from hf`)"),
    ("model.pixel_level_module.", "Hugging Face Mask2Former weights (`pitta-jax convert "
                                  "mask2former --from hf`)"),
    ("sem_seg_head.", "detectron2 Mask2Former weights (`pitta-jax convert mask2former --from "
                      "detectron2`)"),
    ("patch_embed_stages.", "MonoViT's encoder.pth (`pitta-jax convert monovit`)"),
    ("encoder.patch_embed_stages.", "MonoViT's whole-network depth.pth (`pitta-jax convert "
                                    "monovit --depth`)"),
    ("downsample_layers.", "Lite-Mono's encoder.pth (`pitta-jax convert litemono`)"),
    ("convs.X_", "an HR-Depth or MonoViT depth.pth (`pitta-jax convert hrdepth` / `monovit`)"),
    ("encoder.features.", "Lite-HR-Depth's MobileNetV3 encoder (not supported)"),
    ("net.0.", "a MonoDepth2 pose decoder (`pitta-jax convert monodepth2 --pose`)"),
    ("squeeze.", "a MonoDepth2 pose decoder (`pitta-jax convert monodepth2 --pose`)"),
    ("encoder.conv1.", "a ResNet encoder.pth (`pitta-jax convert monodepth2 --encoder`)"),
    ("decoder.0.conv.", "a MonoDepth2 depth.pth (`pitta-jax convert monodepth2 --depth`)"),
)


def shown(items: Sequence[str], sep: str = ", ") -> str:
  """The first `SHOWN_KEYS` of `items` joined by `sep`, then how many more."""
  return first_and_count(items, SHOWN_KEYS, sep)


def layout_of(keys: Iterable[str]) -> str | None:
  """Which converter reads a file with these keys (`LAYOUTS`), or None."""
  keys = list(keys)
  for prefix, converter in LAYOUTS:
    if any(k.startswith(prefix) for k in keys):
      return converter
  return None


def looks_like(keys: Iterable[str]) -> str:
  """The end of a converter's refusal of a file of another network's keys: "; its keys look
  like <what it is and its converter>" (`layout_of`), else "" (keys it does not know)."""
  other = layout_of(keys)
  return f"; its keys look like {other}" if other else ""


def check_keys(path: str, present: Iterable[str], used: Iterable[str],
               ignorable: Callable[[str], bool]) -> None:
  """Raises CheckpointError naming the unexpected keys (in the file, not used, not ignorable)
  and the missing keys (used, not in the file), the first `SHOWN_KEYS` of each, and the
  converter the unexpected keys look like (`LAYOUTS`); does nothing when they match."""
  present, used = set(present), set(used)
  unexpected = sorted(k for k in present - used if not ignorable(k))
  missing = sorted(used - present)
  problems = []
  if unexpected:
    problems.append(f"{len(unexpected)} unexpected keys: {shown(unexpected)}")
  if missing:
    problems.append(f"{len(missing)} missing keys: {shown(missing)}")
  if problems:
    other = layout_of(unexpected) if len(unexpected) > len(present) // 2 else None
    hint = f"; its keys look like {other}" if other else ""
    raise CheckpointError(f"{path}: " + "; ".join(problems) + f" ({len(used)} keys expected)"
                          + hint)
