"""Flax networks: MonoDepth2 (ResNet encoder, depth decoder, pose decoder), Mask2Former."""
