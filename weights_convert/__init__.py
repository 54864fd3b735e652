"""Checkpoint converters: PyTorch / detectron2 / Hugging Face weights -> Flax variables.

Pure NumPy; needs no torch. `python -m weights_convert --help` lists the converters.
"""
