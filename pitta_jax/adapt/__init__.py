"""Online adaptation: config, the scanned step engine, and the method registry."""

from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.engine import (AdaptState, DepthModel, LossAux, Method, StepInput, StepOutput,
                                    adapt_step, adapt_stream, init_state, load_state,
                                    make_chunk_runner, make_optimizer, make_step,
                                    monodepth2_model, save_state)

__all__ = ["AdaptConfig", "AdaptState", "DepthModel", "LossAux", "Method", "StepInput",
           "StepOutput", "adapt_step", "adapt_stream", "init_state", "load_state",
           "make_chunk_runner", "make_optimizer", "make_step", "monodepth2_model", "save_state"]
