"""Mask2Former (Swin backbone, MSDeformAttn pixel decoder, masked-attention transformer decoder):
PITTA's frozen panoptic segmenter (paper Sec. 3.1), the segmenter's entry beside the depth
networks. `model` holds the modules and inference, `load` reads a converted weights directory.
"""

from pitta_jax.models.mask2former.load import CONFIG_JSON, PARAMS_DIR, load_mask2former
from pitta_jax.models.mask2former.model import (InferenceConfig, Mask2Former, Mask2FormerConfig,
                                                mask_logits_to_image, network, predict,
                                                preprocess, resized_shape, segment)

__all__ = ["CONFIG_JSON", "PARAMS_DIR", "load_mask2former", "InferenceConfig", "Mask2Former",
           "Mask2FormerConfig", "mask_logits_to_image", "network", "predict", "preprocess",
           "resized_shape", "segment"]
