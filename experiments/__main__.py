from experiments import main
from pitta_jax.cli import exit_with

exit_with(main())
