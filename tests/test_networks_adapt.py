"""Every registered network through the engine: selectors find its norm layers, PITTA adapts it,
`none` is the network as it is.

References: the network's own eval-mode depth (`Network.depth`) for `none`; hand-counted
selections (no LayerNorm is ever taken for a BatchNorm); one PITTA step must change exactly the
selected leaves. Random weights at the smallest input each network accepts.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax.traverse_util import flatten_dict

from pitta_jax import trainable
from pitta_jax.adapt import AdaptConfig, adapt_stream, init_state, make_chunk_runner, make_optimizer, make_step
from pitta_jax.methods import build
from pitta_jax.methods.depth_refining import DepthRefiningConfig
from pitta_jax.methods.pitta import PittaConfig
from pitta_jax.models.random_init import init_variables
from pitta_jax.models.registry import MODELS, network

import adapt_frames
from xla_options import QUICK_COMPILE

# network -> (config, input (H, W), default selector, its norm kind)
CASES = {
    "sgdepth": ({"num_layers": 18}, (64, 96), "encoder_bn", "bn"),
    "hrdepth": ({"num_layers": 18}, (64, 96), "encoder_bn", "bn"),
    "litemono": ({"height": 192, "width": 640}, (64, 96), "encoder_ln", "ln"),
    "monovit": ({}, (64, 96), "encoder_bn", "bn"),
    "depth_anything_v2": ({"embed_dim": 48, "depth": 4, "num_heads": 3, "layer_idx": [0, 1, 2, 3],
                           "features": 16, "out_channels": [8, 16, 32, 32], "head_features": 8},
                          (56, 84), "encoder_ln", "ln"),
}


def _frames(h: int, w: int):
  f = adapt_frames.make_frames(2, seed=1)
  img = jax.image.resize(jnp.asarray(f.image), (2, h, w, 3), "linear")
  pan = np.asarray(jax.image.resize(jnp.asarray(f.panoptic), (2, h, w), "nearest"))
  return f._replace(image=np.asarray(img, np.float32), panoptic=pan.astype(np.int32))


def test_every_network_is_registered():
  # depth_anything_v2_metric is depth_anything_v2's module with a sigmoid x max_depth head
  # (tests/test_depth_anything_v2.py): the same layers, selectors and engine path
  assert set(CASES) | {"monodepth2", "depth_anything_v2_metric"} == set(MODELS)


def _abstract(name):
  """(network, zero variables with the network's shapes) without compiling anything."""
  config, (h, w), _, _ = CASES[name]
  net = network(name, {"height": h, "width": w, **config})
  shapes = jax.eval_shape(net.module.init, jax.random.PRNGKey(0), jnp.zeros((1, h, w, 3)))
  v = jax.tree_util.tree_map(lambda s: np.zeros(s.shape, s.dtype), shapes)
  return net, {"params": v["params"], "batch_stats": v.get("batch_stats", {})}


@pytest.mark.parametrize("name", sorted(CASES))
def test_selectors_take_the_encoder_norm_layers_of_the_asked_kind(name):
  """encoder_bn takes only layers with running statistics, encoder_ln only those without, both
  under the encoder; fraction follows the module's forward order (its last BN layers)."""
  net, variables = _abstract(name)
  stats = {k.rsplit("/", 1)[0] for k in flatten_dict(variables["batch_stats"], sep="/")}
  scaled = {k[: -len("/scale")] for k in flatten_dict(variables["params"], sep="/")
            if k.startswith(net.spec.encoder + "/") and k.endswith("/scale")}
  for kind in ("bn", "ln"):
    sel = trainable.Selector(f"encoder_{kind}")
    if not {m for m in scaled if (m in stats) == (kind == "bn")}:
      with pytest.raises(ValueError, match="found no (BatchNorm|LayerNorm)"):
        trainable.selected_paths(variables, sel, net.spec.encoder)
      continue
    paths = trainable.selected_paths(variables, sel, net.spec.encoder)
    mods = {p.rsplit("/", 1)[0] for p in paths}
    assert paths and all(p.startswith(net.spec.encoder + "/") for p in paths)
    assert all((m in stats) == (kind == "bn") for m in mods), name
  order = net.forward_order() if name != "depth_anything_v2" else None
  if order is not None and stats:
    last = trainable.selected_paths(variables, trainable.parse_selector("cnn0_bn10"),
                                    net.spec.encoder, order)
    bns = [m for m in order if m in stats and m.startswith(net.spec.encoder + "/")]
    want = bns[len(bns) - int(round(len(bns) * 0.1)):]
    assert [p.rsplit("/", 1)[0] for p in last[::2]] == want


@pytest.mark.parametrize("name", ["depth_anything_v2"])
def test_pitta_and_none_run_on_other_networks(name):
  """A LayerNorm network with relative output (Depth Anything V2) through the engine; the
  BatchNorm networks share MonoDepth2's path (tests/test_adapt.py), the selectors are checked
  above for all, parity in each network's own test file."""
  config, (h, w), selector, kind = CASES[name]
  net = network(name, {"height": h, "width": w, **config})
  variables = init_variables(net.module, 0, jnp.zeros((1, h, w, 3)))
  variables = {"params": variables["params"], "batch_stats": variables.get("batch_stats", {})}
  sel = trainable.parse_selector(selector)
  frames = _frames(h, w)
  cfg = AdaptConfig(selector=selector, chunk_size=2, lr=1e-3)
  pitta = build("pitta", PittaConfig(ld=DepthRefiningConfig(max_instances=4, window=3)))
  depths = {}
  for method in (pitta, build("none")):
    tx = make_optimizer(cfg)
    state, consts = init_state(variables, method, cfg, tx, net)
    runner = make_chunk_runner(make_step(net, method, cfg, tx), QUICK_COMPILE)
    (state, out), = adapt_stream(state, consts, [frames], runner)
    assert np.all(np.isfinite(out.depth)) and not np.any(out.skipped)
    depths[method.name] = out.depth
    before = flatten_dict(trainable.split(variables, sel, net.spec.encoder).trainable, sep="/")
    after = flatten_dict(state.trainable, sep="/")
    moved = [k for k in after if not np.array_equal(np.asarray(after[k]), np.asarray(before[k]))]
    if method.name == "pitta":
      assert moved and np.isfinite(out.loss).all() and out.logs["n_instances"][0] == 3
    else:
      assert not moved
  # none with batch statistics = the network's own depth with batch statistics, frame by frame
  depth = jax.jit(lambda v, x: net.depth(v, x, True))
  ref = np.stack([np.asarray(depth(variables, jnp.asarray(frames.image[t:t + 1])))[0]
                  for t in range(2)])
  # (compared as inverse depth: a relative network's near-zero outputs make depth 1 / eps)
  inv = lambda d: 1.0 / np.asarray(d, np.float64)
  tol = 1e-5 * float(np.max(inv(ref)))
  np.testing.assert_allclose(inv(depths["none"]), inv(ref), rtol=1e-5, atol=tol)
  # predict-then-adapt: PITTA's first frame is the unadapted network
  np.testing.assert_allclose(inv(depths["pitta"][0]), inv(ref[0]), rtol=1e-5, atol=tol)
