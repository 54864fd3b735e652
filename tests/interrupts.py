"""A Ctrl-C that lands while a compiled chunk runs, for the tests of the runs' interrupts."""

from __future__ import annotations


def interrupt_a_wait(monkeypatch, which: int) -> None:
  """Raises KeyboardInterrupt from the first poll of the `which`-th chunk's wait (1-based;
  `engine.wait_for_chunk`), as the signal handler raises it inside the wait's loop."""
  from pitta_jax.adapt import engine
  real, waits = engine._all_ready, []

  def polled(leaves):
    if not any(leaves is seen for seen in waits):
      waits.append(leaves)
      if len(waits) == which:
        raise KeyboardInterrupt
    return real(leaves)
  monkeypatch.setattr(engine, "_all_ready", polled)
