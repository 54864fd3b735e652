from pitta_jax.cli import exit_with, interruptible


def _main() -> int:
  from weights_convert.cli import main  # imported inside: a Ctrl-C while it loads is handled
  return main()


exit_with(interruptible(_main))
