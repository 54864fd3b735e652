"""Online adaptation: config, the scanned step engine, and many-stream variants."""

from pitta_jax.adapt.config import AdaptConfig
from pitta_jax.adapt.engine import (AdaptState, Consts, StepInput, StepOutput, adapt_step,
                                    adapt_stream, init_state, load_state, make_chunk_runner,
                                    make_method_runner, make_optimizer, make_step, optax_update,
                                    save_state)

__all__ = ["AdaptConfig", "AdaptState", "Consts", "StepInput", "StepOutput", "adapt_step",
           "adapt_stream", "init_state", "load_state", "make_chunk_runner", "make_method_runner",
           "make_optimizer", "make_step", "optax_update", "save_state"]
