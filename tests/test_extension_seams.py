"""The extension seams a user reaches from the README: a depth network and a TTA method of one's
own, registered at run time and run through the public API (weights files, the engine, the
commands in-process), and the library used inside one's own program (`jax.jit`, the process's
logging left alone).

References: a third-party Flax network built on `flax.linen.BatchNorm` (which README's 'Adding a
network' allows), whose encoder BatchNorms get Flax's names (`BatchNorm_0`, ...); `tests/tiny_net`
for the engine; the process's own logging state before and after a call.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pitta_jax.adapt import AdaptConfig, init_state, make_method_runner, make_optimizer
from pitta_jax.adapt.inputs import chunks
from pitta_jax.checkpoint import WeightsError, save_weights
from pitta_jax.data.synthetic import SyntheticConfig, generate_sequence
from pitta_jax.methods import build
from pitta_jax.models.registry import MODELS, Network
from pitta_jax.models.spec import ModelSpec
from tiny_net import TINY, tiny_variables

H, W = 64, 96
ROOT = Path(__file__).resolve().parents[1]


class FlaxBnEncoder(nn.Module):
  """Two strided convolutions, each with a `flax.linen.BatchNorm` (Flax's default names)."""

  @nn.compact
  def __call__(self, x: jax.Array, train: bool = False) -> list[jax.Array]:
    f1 = nn.relu(nn.BatchNorm(use_running_average=not train)(nn.Conv(8, (3, 3), strides=2)(x)))
    f2 = nn.relu(nn.BatchNorm(use_running_average=not train)(nn.Conv(16, (3, 3), strides=2)(f1)))
    return [f1, f2]


class FlaxBnNet(nn.Module):
  """A third-party depth network: sigmoid disparities, full resolution first."""
  encoder_name: str = "encoder"

  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array, ...]:
    f1, f2 = FlaxBnEncoder(name=self.encoder_name)((images - 0.45) / 0.225, train)
    up = jax.image.resize(f2, images.shape[:3] + (f2.shape[-1],), "bilinear")
    return (nn.sigmoid(nn.Conv(1, (3, 3), name="head0")(up)),
            nn.sigmoid(nn.Conv(1, (3, 3), name="head1")(f2)))


MYNET = ModelSpec(name="mynet", build=lambda config: FlaxBnNet(), output="sigmoid_disparity",
                  size_multiple=8, default_size=(H, W))


def _variables(module: nn.Module) -> dict:
  return module.init(jax.random.PRNGKey(0), jnp.zeros((1, H, W, 3)))


def test_save_weights_of_an_unregistered_network_says_how_to_register(tmp_path):
  """README: a network of one's own is saved with the checkpoint helpers; before it is in
  `MODELS`, `save_weights` raised a bare KeyError('tiny') instead of a WeightsError naming the
  registry, and wrote nothing."""
  assert "tiny" not in MODELS
  with pytest.raises(WeightsError, match=r"'tiny'.*MODELS\[spec.name\] = spec"):
    save_weights(tmp_path / "w", "tiny", {"height": H, "width": W},
                 jax.device_get(tiny_variables(0)))
  assert not (tmp_path / "w").exists()


def test_a_chunk_runner_runs_inside_the_callers_own_jit():
  """`make_method_runner`'s runner inside a user's `jax.jit`: it passed XLA compiler options
  (the CPU convolution library) to a nested `jax.jit`, which JAX refuses ("`compiler_options`
  can only be passed to top-level `jax.jit`"). Inside, it gives the runner's own depths."""
  method, cfg = build("pitta"), AdaptConfig(chunk_size=2)
  tx = make_optimizer(cfg, method)
  runner = make_method_runner(TINY, method, cfg, tx)
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=2, domain="fog"))
  chunk = next(iter(chunks(frames, H, W, cfg.chunk_size, cfg.max_segments)))[0]
  state, consts = init_state(tiny_variables(0), method, cfg, tx, TINY)
  copy = jax.tree_util.tree_map(jnp.copy, state)
  _, direct = runner(state, chunk, consts)
  _, nested = jax.jit(lambda s, f, c: runner(s, f, c))(copy, chunk, consts)
  np.testing.assert_allclose(np.asarray(nested.depth), np.asarray(direct.depth), rtol=1e-5)


def test_actmad_on_a_flax_batchnorm_network_names_its_flag_and_layers():
  """ActMAD's default layers are MonoDepth2's BatchNorm names; on a network of one's own built
  on `flax.linen.BatchNorm` they match nothing, and the error named neither the flag that
  changes them nor the layers there are. With the regex it offers, the statistics come."""
  from pitta_jax.methods import actmad
  net = Network(MYNET, FlaxBnNet())
  variables = _variables(net.module)
  images = [np.random.default_rng(0).random((2, H, W, 3), np.float32)]
  with pytest.raises(ValueError, match=r"--actmad.layers.*encoder/BatchNorm_0, "
                                       r"encoder/BatchNorm_1"):
    actmad.source_statistics(net, variables, images)
  stats = actmad.source_statistics(net, variables, images, r"encoder/BatchNorm_\d+")
  assert sorted(stats) == ["encoder/BatchNorm_0", "encoder/BatchNorm_1"]


def test_a_network_whose_encoder_has_another_name_is_told_about_modelspec_encoder():
  """A network of one's own whose encoder module is not called `encoder` (the `ModelSpec`
  default): the selector's error suggested `encoder_bn`, the selector that had just failed,
  instead of naming `ModelSpec.encoder` and the network's top-level modules."""
  module = FlaxBnNet(encoder_name="backbone")
  spec = ModelSpec(name="mynet2", build=lambda config: module, output="sigmoid_disparity",
                   size_multiple=8, default_size=(H, W))
  net, method, cfg = Network(spec, module), build("pitta"), AdaptConfig()
  with pytest.raises(ValueError, match=r"ModelSpec.encoder.*backbone"):
    init_state(_variables(module), method, cfg, make_optimizer(cfg, method), net)


def test_weights_files_leave_the_root_logger_alone(tmp_path):
  """`save_weights`/`load_weights` (and every checkpoint) go through orbax, which logs through
  absl, and absl runs `logging.basicConfig()` while the root logger has no handler: a stderr
  handler stayed on the root logger, and the caller's own `logging.basicConfig(...)` afterwards
  did nothing. In a fresh process (pytest's own handlers sit on the root logger)."""
  script = textwrap.dedent(f"""
      import logging, sys
      sys.path.insert(0, {str(ROOT / "tests")!r})
      import jax
      from tiny_net import TINY, tiny_variables
      from pitta_jax.checkpoint import load_weights, save_weights
      from pitta_jax.models.registry import MODELS
      MODELS["tiny"] = TINY.spec
      save_weights({str(tmp_path / "w")!r}, "tiny", {{"height": 64, "width": 96}},
                   jax.device_get(tiny_variables(0)))
      load_weights({str(tmp_path / "w")!r})
      print(len(logging.root.handlers))
      """)
  env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
  out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                       cwd=tmp_path, timeout=120)
  assert out.returncode == 0, out.stderr[-2000:]
  assert out.stdout.split() == ["0"], out.stdout


def test_the_commands_run_in_process_leave_the_log_levels_as_they_were(tmp_path, monkeypatch):
  """The commands on a network of one's own run from a script (`pitta_jax.cli.main(argv)`
  after registering it): the command silenced OpenCV's and absl's logs for the rest of the
  caller's process; an interrupted one (Ctrl-C, exit 130) did too."""
  import cv2.utils.logging as cv_logging
  from pitta_jax import cli
  absl = logging.getLogger("absl")
  before = (cv_logging.getLogLevel(), absl.level)
  assert cli.main(["predict", "--weights", str(tmp_path / "none"), "--images", str(tmp_path),
                   "--out", str(tmp_path / "out")]) == 2
  assert (cv_logging.getLogLevel(), absl.level) == before

  def interrupted(argv):
    raise KeyboardInterrupt
  monkeypatch.setattr(cli, "_main", interrupted)
  monkeypatch.setattr(sys, "unraisablehook", sys.unraisablehook)  # the teardown's, put back
  assert cli.main(["predict"]) == 130
  assert (cv_logging.getLogLevel(), absl.level) == before


def test_a_method_registered_under_another_name_than_its_own_is_refused(monkeypatch):
  """`METHODS["mine"] = (Config, build)` with a `build` whose `Method` is named "mymethod": the
  runs took the method's name and the CLI then refused the method's own flags with "--mine.w is
  a flag of --method mine, not of --method mymethod"; `build` now says what to register."""
  import dataclasses
  from pitta_jax import methods
  from pitta_jax.methods.base import Aux, Method

  @dataclasses.dataclass(frozen=True)
  class MineConfig:
    w: float = 1.0

  def make(config: MineConfig) -> Method:
    def loss(trainable, *, frame, **_):
      return jnp.zeros(()), Aux(frame.image[..., 0], {})
    return Method("mymethod", config, init=lambda *a: {}, loss=loss)

  monkeypatch.setitem(methods.METHODS, "mine", (MineConfig, make))
  with pytest.raises(ValueError, match=r"METHODS\['mine'\] builds a method named 'mymethod'"):
    methods.build("mine")


NOTEBOOK_CELL = """
import flax.linen as nn
from pitta_jax.models.spec import ModelSpec

class Net(nn.Module):
  @nn.compact
  def __call__(self, images, train=False):
    x = nn.Conv(4, (3, 3), name="conv")(images)
    return (nn.sigmoid(SCALE * nn.Conv(1, (3, 3), name="head")(x)),)

spec = ModelSpec("cellnet", build=lambda config: Net(), output="sigmoid_disparity",
                 size_multiple=8, default_size=(64, 96))
"""


def test_a_shared_runners_cache_sees_a_network_class_defined_again():
  """A notebook cell that defines the network, edited and run again, binds `Net` to a new
  class while its spec's `lambda config: Net()` keeps equal code: a shared `run.Runners` (as
  its docstring advises for a sweep) served the first network's compiled step, and the second
  run reported the old network's depths."""
  from pitta_jax.checkpoint import Weights
  from pitta_jax.run import Runners, run_sequence
  frames = generate_sequence(SyntheticConfig(height=H, width=W, num_frames=1, domain="fog"))
  cfg = AdaptConfig(method="none", bn_stats="running", selector="all")
  runners, namespace = Runners(), {}
  for scale in (1.0, 3.0):
    exec(NOTEBOOK_CELL.replace("SCALE", repr(scale)), namespace)
    spec, module = namespace["spec"], namespace["Net"]()
    variables = module.init(jax.random.PRNGKey(0), jnp.zeros((1, H, W, 3)))
    run = run_sequence(Weights(spec, {"height": H, "width": W}, variables), frames, cfg,
                       quiet=True, runners=runners, keep=[0])
    own = spec.to_depth(module.apply(variables, jnp.asarray(frames[0].image[None]))[0][..., 0])
    np.testing.assert_allclose(run.kept_depths[0], np.asarray(own)[0], rtol=1e-5,
                               err_msg=f"SCALE {scale}")
