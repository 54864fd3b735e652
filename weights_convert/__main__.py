from pitta_jax.cli import exit_with
from weights_convert.cli import main

exit_with(main())
