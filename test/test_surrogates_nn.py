"""Neural-network surrogates and the wear diagnosis: the exported kernel against numpy and
torch, the training algorithms on small problems, the shipped artefacts on freshly generated
maps, the parameter check and the torch-free import."""

import math

import numpy as np
import pytest

from eha_ros.physics import default_params
from eha_ros.physics.maps import WEAR_RANGES, spool_grid, transient_map
from eha_ros.physics.params import replace
from eha_ros.health import valve_test
from eha_ros.surrogates import nn
from eha_ros.training import networks
from eha_ros.training import nn as nn_train
from eha_ros.training import valve_test as valve_test_training
from eha_ros.artefacts import ArtefactError
from eha_ros.surrogates.base import FluidSurrogate, SurrogateError, relative_error
from eha_ros.surrogates.registry import load_surrogate
from eha_ros.training.database import heldout_maps

RNG = np.random.default_rng(20240611)


def _random_inputs(n, rng):
    p = default_params()
    return np.stack([rng.uniform(-p.spool_stroke_m, p.spool_stroke_m, n),
                     rng.uniform(-6e-5, 6e-5, n),
                     rng.uniform(*WEAR_RANGES['overlap_m'], n),
                     rng.uniform(*WEAR_RANGES['radial_clearance_m'], n)], axis=1)


def _random_packed(sizes, sources, transforms, rng, seed=0):
    """A packed MLP with random weights and a normalisation fitted on random inputs."""
    torch = pytest.importorskip('torch')
    raw = _random_inputs(500, rng)
    scales = [default_params().spool_stroke_m / math.sinh(4.0), None, None, None]
    inputs = nn.fit_inputs(raw, sources, transforms, [scales[s] for s in sources])
    model = networks.make_torch_mlp(d_in=sizes[0], d_hidden=sizes[1:-1], seed=seed)
    with torch.no_grad():  # non-zero biases too
        model.theta.add_(0.3 * torch.randn(model.theta.shape, dtype=torch.float64,
                                           generator=torch.Generator().manual_seed(seed)))
    return nn.pack(model.sizes, inputs, np.array([2e6, 1.3e8]), model.theta.detach().numpy()), \
        model, inputs


@pytest.mark.parametrize('sizes,sources,transforms', [
    ([4, 21, 15, 3, 1], [0, 1, 2, 3], ['asinh', 'linear', 'linear', 'linear']),
    ([4, 21, 15, 3, 1], [0, 1, 2, 3], ['linear'] * 4),
    ([2, 32, 32, 1], [0, 1], ['linear', 'linear']),
])
def test_kernel_matches_numpy_and_torch(sizes, sources, transforms):
    torch = pytest.importorskip('torch')
    data, model, inputs = _random_packed(sizes, sources, transforms, RNG)
    raw = _random_inputs(2000, RNG)
    s = FluidSurrogate('t', nn.mlp_kernel, data, {'kind': 'mlp'})
    got = s.p12(*raw.T)
    ref = nn.mlp_numpy(data, *raw.T)
    scale = np.max(np.abs(ref))
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12 * scale)
    with torch.no_grad():
        model.eval()
        y = model(torch.as_tensor(nn.transform_inputs(inputs, raw)))[:, 0].numpy()
    np.testing.assert_allclose(got, 2e6 + 1.3e8 * y, rtol=1e-6, atol=1e-6 * scale)
    # a 2-input network ignores the wear arguments
    if len(sources) == 2:
        np.testing.assert_array_equal(s.p12(raw[:, 0], raw[:, 1], 0.0, 1e-6), got)


def test_jacobian_by_hand_matches_autograd():
    torch = pytest.importorskip('torch')
    from torch.func import jacrev, vmap
    for d_out in (1, 2):
        model = networks.make_torch_mlp(d_in=3, d_hidden=[5, 4], d_out=d_out, seed=1)
        x = torch.randn(7, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
        theta = model.theta.detach()
        ref = vmap(jacrev(lambda th, xi: model(xi[None], th)[0]), in_dims=(None, 0))(theta, x)
        np.testing.assert_allclose(model.jacobian(x).numpy(),
                                   ref.reshape(7 * d_out, -1).numpy(), rtol=1e-12, atol=1e-13)


def _tiny_problem():
    torch = pytest.importorskip('torch')
    x = torch.linspace(-1.0, 1.0, 200, dtype=torch.float64)[:, None]
    y = 0.8 * torch.sin(2.5 * x) * torch.exp(-x ** 2)
    return x, y


def test_lm_fits_small_regression_and_beats_gradient_descent():
    torch = pytest.importorskip('torch')
    x, y = _tiny_problem()
    lm = networks.make_torch_mlp(d_in=1, d_hidden=[6], seed=0)
    start = networks._mse(lm, x, y)
    hist = networks.train_lm(lm, networks.Split(x, y), networks.LMSettings(epochs=60),
                             threads=1)
    loss_lm = networks._mse(lm, x, y)
    assert hist['epochs'] == 60 or hist['stop'] in ('mu_max', 'min_grad')
    assert loss_lm < 1e-6 * start
    gd = networks.make_torch_mlp(d_in=1, d_hidden=[6], seed=0)
    opt = torch.optim.SGD(gd.parameters(), lr=0.2)
    for _ in range(600):  # ten times LM's epochs
        opt.zero_grad()
        loss = torch.mean((gd(x) - y) ** 2)
        loss.backward()
        opt.step()
    loss_gd = networks._mse(gd, x, y)
    assert loss_lm < 1e-3 * loss_gd


@pytest.mark.parametrize('algorithm', ['lm', 'adam_lbfgs'])
def test_training_is_reproducible(algorithm):
    pytest.importorskip('torch')
    x, y = _tiny_problem()
    thetas = []
    for _ in range(2):
        model = networks.make_torch_mlp(d_in=1, d_hidden=[4, 3], seed=7)
        if algorithm == 'lm':
            networks.train_lm(model, networks.Split(x, y, x[::3], y[::3]),
                              networks.LMSettings(epochs=20, subsample=64, resample_every=5),
                              seed=7, threads=1)
        else:
            networks.train_adam_lbfgs(model, networks.Split(x, y, x[::3], y[::3]),
                                      networks.AdamLBFGSSettings(adam_steps=50, batch=32,
                                                                 lbfgs_iters=20, val_every=10),
                                      seed=7, threads=1)
        thetas.append(model.theta.detach().numpy().copy())
    np.testing.assert_array_equal(thetas[0], thetas[1])


# --- shipped artefacts ----------------------------------------------------------------------

@pytest.fixture(scope='module')
def fresh_maps():
    """Three maps at random wear inside the ranges, on the database grid (DB2 flows)."""
    return heldout_maps(3, q_max_m3_s=6e-5, n_q=15, seed=777)


@pytest.mark.parametrize('name', ['nn', 'nn2'])
def test_shipped_kernel_matches_numpy(name):
    s = load_surrogate(name)
    raw = _random_inputs(3000, RNG)
    ref = nn.mlp_numpy(s.data, *raw.T)
    np.testing.assert_allclose(s.p12(*raw.T), ref, rtol=1e-12,
                               atol=1e-12 * np.max(np.abs(ref)))
    assert s.meta['fluid_hash'] and s.meta['training']['algorithm'] in ('lm', 'adam_lbfgs')


#: Bounds on the relative error in Euclidean norm of a fresh map (the reference reached
#: 1-5 %; the shipped networks' held-out errors are about 0.2 % over DB2's flows, 0.6 % over
#: DB3's narrow flows and 0.15 % for the 2-input network).
NN_MAP_BOUND = 0.005
NN_MAP_BOUND_NARROW_FLOWS = 0.012
NN2_MAP_BOUND = 0.005


@pytest.mark.parametrize('q_max,bound', [(6e-5, NN_MAP_BOUND),
                                         (1.5e-5, NN_MAP_BOUND_NARROW_FLOWS)])
def test_shipped_nn_on_fresh_maps(fresh_maps, q_max, bound):
    s = load_surrogate('nn')
    maps = fresh_maps if q_max == 6e-5 else heldout_maps(3, q_max_m3_s=q_max, n_q=15,
                                                         seed=777)
    for xs, q, lap, clr, p12 in maps:
        pred = s.p12(xs[:, None], q[None, :], lap, clr)
        assert relative_error(pred, p12) < bound


def test_shipped_nn2_on_fresh_nominal_map():
    p = default_params()
    s = load_surrogate('nn2')
    xs = spool_grid(133, p.spool_stroke_m)
    # flows between the database's (DB5: 133 flows over +-6e-5)
    q = np.linspace(-6e-5, 6e-5, 133)
    q = 0.5 * (q[1:] + q[:-1])[::9]
    p12 = transient_map(xs[:, None], q[None, :], params=p)['p12_pa']
    pred = s.p12(xs[:, None], q[None, :], 5e-6, 5e-6)   # wear arguments are ignored
    assert relative_error(pred, p12) < NN2_MAP_BOUND


#: Bounds on the per-map wear error (median of the map's curves), % of each parameter's range
#: (held-out maps of DB4: about 0.07 % on average, 0.4 % at worst; 0.3 % and 1 % with 1 %
#: noise).
DIAG_BOUND_CLEAN = 0.5
DIAG_BOUND_NOISY = 1.0


@pytest.mark.parametrize('noise', [0.0, 0.01])
def test_shipped_diag_recovers_wear(fresh_maps, noise):
    rng = np.random.default_rng(5)
    ranges = np.array([np.diff(WEAR_RANGES['radial_clearance_m'])[0],
                       np.diff(WEAR_RANGES['overlap_m'])[0]])
    bound = DIAG_BOUND_NOISY if noise else DIAG_BOUND_CLEAN
    for xs, q, lap, clr, p12 in fresh_maps:
        curves = valve_test_training.add_noise(p12.T, noise, rng).T if noise else p12
        est = valve_test.estimate_wear_map(curves, q)
        err = np.abs([est.radial_clearance_m - clr, est.overlap_m - lap]) / ranges * 100
        assert np.all(err < bound), (lap, clr, est)
        assert est.curves_used == q.size and est.radial_clearance_std_m >= 0.0
        c1, o1 = valve_test.estimate_wear(curves[:, 3], q[3])
        assert c1 == pytest.approx(est.per_curve_clearance_m[3], rel=1e-12)
        assert o1 == pytest.approx(est.per_curve_overlap_m[3], rel=1e-12, abs=1e-18)


def test_diag_rejects_wrong_curve_length():
    with pytest.raises(ValueError, match='spool grid'):
        valve_test.estimate_wear(np.zeros(100), 0.0)


def test_other_fluid_parameters_are_refused():
    other = replace(default_params(), supply_pressure_pa=default_params().supply_pressure_pa * 1.1)
    for name in ('nn', 'nn2'):
        with pytest.raises(SurrogateError, match='fluid parameters'):
            load_surrogate(name, params=other)
    with pytest.raises(ArtefactError, match='fluid parameters'):
        valve_test.load_diagnostic(params=other)


def test_both_network_families_train_through_one_trainer():
    """The fluid networks and the diagnostic network share ``networks.fit_network``: with the
    same normalised data, seed and settings each gives the trainer's own network."""
    pytest.importorskip('torch')
    rng = np.random.default_rng(3)
    raw = _random_inputs(300, rng)
    y = np.sin(raw[:, 0] / 1e-4) * 1e7 + raw[:, 1] * 1e11
    st = {'epochs': 5, 'subsample': 1000}
    data, _, _, _ = nn_train._fit_model(networks.Split(raw, y, raw[::3], y[::3]),
                                        ([0, 1], ['linear', 'linear'], None), hidden=[5],
                                        algorithm='lm', seed=4, settings=st, threads=1)
    inputs, output = nn.fit_inputs(raw, [0, 1], ['linear', 'linear']), nn.fit_output(y)
    ref, _, _ = networks.fit_network(networks.Split(nn.transform_inputs(inputs, raw),
                                                    (y - output[0]) / output[1],
                                                    nn.transform_inputs(inputs, raw[::3]),
                                                    (y[::3] - output[0]) / output[1]),
                                     hidden=[5],
                                     algorithm='lm', seed=4, settings=st, threads=1)
    np.testing.assert_array_equal(data[3], ref.theta.detach().numpy())
    x2 = np.stack([raw[:, 0], raw[:, 1] * 3.0], axis=1)
    y2 = np.stack([y, -y], axis=1)
    weights, in_norm, out_norm, _, _ = valve_test_training._train_one(
        x2, y2, x2[::3], y2[::3], hidden=[5], algorithm='lm', seed=4, settings=st, threads=1)
    in2, out2 = networks.minmax(x2), networks.minmax(y2)
    ref2, _, _ = networks.fit_network(networks.Split((x2 - in2[0]) / in2[1],
                                                     (y2 - out2[0]) / out2[1],
                                                     (x2[::3] - in2[0]) / in2[1],
                                                     (y2[::3] - out2[0]) / out2[1]),
                                      hidden=[5],
                                      algorithm='lm', seed=4, settings=st, threads=1)
    for (w, b), (wr, br) in zip(weights, ref2.layers()):
        np.testing.assert_array_equal(w, wr.detach().numpy())
        np.testing.assert_array_equal(b, br.detach().numpy())
