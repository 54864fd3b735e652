"""Every registered network through the engine: selectors find its norm layers, PITTA adapts it,
`none` is the network as it is.

References: the network's own eval-mode depth (`Network.depth`) for `none`; hand-counted
selections (no LayerNorm is ever taken for a BatchNorm); one PITTA step must change exactly the
selected leaves. Random weights at the smallest input each network accepts.
"""

from __future__ import annotations

import flax.linen as nn
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
from pitta_jax.models.registry import MODELS, Network, network
from pitta_jax.models.spec import ModelSpec

import adapt_frames

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
    runner = make_chunk_runner(make_step(net, method, cfg, tx))
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


class _FlaxBnEncoder(nn.Module):
  """conv 3x3 -> flax.linen.BatchNorm -> ReLU: a user's own Flax layers, not `layers.BatchNorm`."""

  @nn.compact
  def __call__(self, x: jax.Array, train: bool) -> jax.Array:
    x = nn.Conv(8, (3, 3), padding=((1, 1), (1, 1)), use_bias=False, name="conv1")(x)
    return nn.relu(nn.BatchNorm(use_running_average=not train, momentum=0.9, epsilon=1e-5,
                                name="bn1")(x))


class _FlaxBnNet(nn.Module):
  @nn.compact
  def __call__(self, images: jax.Array, train: bool = False) -> tuple[jax.Array]:
    return (nn.sigmoid(nn.Conv(1, (1, 1), name="head")(_FlaxBnEncoder(name="encoder")(images,
                                                                                      train))),)


def _torch_flax_bn_net(variables, images: np.ndarray, train: bool) -> np.ndarray:
  """`_FlaxBnNet` as a PyTorch user writes it (Conv2d, BatchNorm2d in train or eval mode)."""
  import torch
  p, s = variables["params"], variables["batch_stats"]["encoder"]["bn1"]
  t = lambda a: torch.tensor(np.asarray(a, np.float32))
  conv1 = torch.nn.Conv2d(3, 8, 3, padding=1, bias=False)
  bn = torch.nn.BatchNorm2d(8, eps=1e-5, momentum=0.1)
  head = torch.nn.Conv2d(8, 1, 1)
  with torch.no_grad():
    conv1.weight.copy_(t(p["encoder"]["conv1"]["kernel"]).permute(3, 2, 0, 1))
    bn.weight.copy_(t(p["encoder"]["bn1"]["scale"]))
    bn.bias.copy_(t(p["encoder"]["bn1"]["bias"]))
    bn.running_mean.copy_(t(s["mean"]))
    bn.running_var.copy_(t(s["var"]))
    head.weight.copy_(t(p["head"]["kernel"]).permute(3, 2, 0, 1))
    head.bias.copy_(t(p["head"]["bias"]))
    net = torch.nn.Sequential(conv1, bn, torch.nn.ReLU(), head, torch.nn.Sigmoid())
    net.train(train)
    out = net(t(images).permute(0, 3, 1, 2))
  return out.permute(0, 2, 3, 1).numpy()


def test_a_flax_linen_batchnorm_network_adapts_with_batch_statistics():
  """A network built on flax.linen.BatchNorm runs under bn_stats='batch' (PITTA's default):
  its disparities are PyTorch's train-mode ones (the frame's statistics), PITTA moves its
  encoder BN scale/bias, and its running statistics stay as they were."""
  net = Network(ModelSpec(name="flax_bn", build=lambda config: _FlaxBnNet(),
                          output="sigmoid_disparity", size_multiple=1, default_size=(64, 96)),
                _FlaxBnNet())
  variables = net.module.init(jax.random.PRNGKey(0), jnp.zeros((1, 64, 96, 3)))
  rng = np.random.default_rng(0)
  variables = {"params": variables["params"],
               "batch_stats": {"encoder": {"bn1": {"mean": rng.normal(size=8).astype(np.float32),
                                                   "var": rng.uniform(0.5, 2, 8).astype(np.float32)}}}}
  frames = _frames(64, 96)
  for train in (True, False):
    got = np.asarray(jax.jit(lambda v, x, train=train: net.outputs(v, x, train)[0])(
        variables, frames.image))
    np.testing.assert_allclose(got, _torch_flax_bn_net(variables, frames.image, train),
                               rtol=1e-5, atol=1e-6)
  _, acts = net.capture(variables, frames.image[:1], True, r"encoder/bn1")
  assert acts["encoder/bn1"].shape == (1, 64, 96, 8)

  cfg = AdaptConfig(chunk_size=2, lr=1e-2)
  assert cfg.bn_stats == "batch" and cfg.selector == "encoder_bn"
  method = build("pitta", PittaConfig(ld=DepthRefiningConfig(max_instances=4, window=3)))
  tx = make_optimizer(cfg)
  state, consts = init_state(variables, method, cfg, tx, net)
  runner = make_chunk_runner(make_step(net, method, cfg, tx))
  (state, out), = adapt_stream(state, consts, [frames], runner)
  assert np.isfinite(out.loss).all() and not np.any(out.skipped)
  assert sorted(flatten_dict(state.trainable, sep="/")) == ["encoder/bn1/bias", "encoder/bn1/scale"]
  assert not np.array_equal(np.asarray(state.trainable["encoder"]["bn1"]["scale"]),
                            np.asarray(variables["params"]["encoder"]["bn1"]["scale"]))
  # predict-then-adapt: the first frame's depth is the unadapted network's, batch statistics
  want = net.spec.to_depth(_torch_flax_bn_net(variables, frames.image[:1], True)[0, ..., 0])
  np.testing.assert_allclose(np.asarray(out.depth[0]), np.asarray(want), rtol=1e-5)
  for k, v in flatten_dict(consts.batch_stats, sep="/").items():
    np.testing.assert_array_equal(np.asarray(v), flatten_dict(variables["batch_stats"], sep="/")[k])


@pytest.mark.parametrize("name", sorted(CASES))
def test_table3_adapts_norm_layers_that_each_network_has(name):
  """Table 3's PITTA on each network: the selector it gives (BatchNorm for the CNN encoders,
  LayerNorm for Depth Anything V2's ViT) selects that encoder's norm layers, not nothing."""
  from experiments.table3 import NETWORKS
  net, variables = _abstract(name)
  selector = trainable.Selector(NETWORKS[name][1])
  paths = trainable.selected_paths(variables, selector, net.spec.encoder)
  assert paths and all(p.startswith(net.spec.encoder + "/") for p in paths)
  assert all(p.endswith(("/scale", "/bias")) for p in paths)



def test_fraction_selectors_on_networks_with_layernorms_and_dense_layers():
  """fraction(cnn=a, bn=b) on a network without BatchNorm (Depth Anything V2's ViT) takes its
  LayerNorms as the norm layers; its 'cnn' share counts convolution kernels only (4-D), not
  the transformers' Dense kernels (Lite-Mono's pointwise layers, MonoViT's attention)."""
  net, variables = _abstract("depth_anything_v2")
  every_ln = trainable.selected_paths(variables, trainable.Selector("encoder_ln"),
                                      net.spec.encoder)
  all_norms = trainable.selected_paths(variables, trainable.parse_selector("fraction(cnn=0,bn=100)"),
                                       net.spec.encoder)
  assert all_norms and sorted(all_norms) == sorted(every_ln)
  for name in ("litemono", "monovit"):
    net, variables = _abstract(name)
    flat = flatten_dict(variables["params"], sep="/")
    paths = trainable.selected_paths(variables, trainable.parse_selector("fraction(cnn=100,bn=0)"),
                                     net.spec.encoder, net.forward_order())
    kernels = [p for p in paths if p.endswith("/kernel")]
    assert kernels and all(flat[p].ndim == 4 for p in kernels), name
    dense = [k for k in flat if k.startswith(net.spec.encoder + "/") and k.endswith("/kernel")
             and flat[k].ndim == 2]
    assert dense and not set(dense) & set(paths), name
