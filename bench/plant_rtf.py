"""Real-time factor of the high-fidelity closed loop on one core.

Prints one JSON object: simulated seconds per wall second at dt = 1 us, with the controller
evaluated every plant step (the reference's continuous PID) and at 1 kHz (the ROS graph's
rate), for a step and a sine command; best of ``--repeat`` runs after a warm-up (JIT
compilation excluded and reported separately).

With ``--models`` (default: every shipped surrogate) it adds one row per fluid model: the
plant with that surrogate in place of the hf fluid block, controller at 1 kHz, same commands,
at dt = 1 us and, for hf and the dynamic surrogates, at each of ``--large-dts`` (the larger
steps at which ``bench/inloop.py`` measures them against hf at 1 us): wall seconds per simulated
second and the ratio to hf's at 1 us.

With the split integrator (``integrator='split'``: the chamber pressures implicit, the
first stage and spool substepped at 1 us), hf and the dynamic surrogates are also timed at each
of ``--split-dts`` (rows ``model@split@dt=...``, with their real-time factor), and every row
says its cost against hf at the same step and integrator (``cost_vs_hf_same_step``).

    python bench/plant_rtf.py [--duration 1.0] [--repeat 3] [--models dlut,dnn,dga,lut,...]
        [--large-dts 2e-6,5e-6] [--split-dts 1e-5,2e-5,2.5e-5]

``--against REV`` instead measures hf at dt = 1 us (both controller cases, both commands) of
this checkout and of the git revision ``REV`` side by side, in one run: ``REV`` is checked out
into a temporary worktree and each tree is timed in a fresh process of its own (its own
``eha_ros`` source and ``config/``, ``NUMBA_NUM_THREADS=1``), the two alternating for
``--rounds`` rounds (best of ``--repeat`` runs in each round, after a warm-up that compiles);
per case the best real-time factor of each tree over all rounds and the ratio (this checkout
over ``REV``; above 1: faster now), each round's figures and the load averages.

    python bench/plant_rtf.py --against d4243cf [--rounds 3] [--repeat 5] [--duration 0.5]
"""

import argparse
import json
import os
from pathlib import Path
import platform
import shutil
import subprocess
import sys
import tempfile
import time

os.environ.setdefault('NUMBA_NUM_THREADS', '1')

from eha_ros.graph import DYNAMIC_MODELS, MODELS  # noqa: E402
from eha_ros.physics import default_params, simulate  # noqa: E402
from eha_ros.surrogates.registry import load_surrogate  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]
#: The cases ``--against`` times: (scenario, label, controller period [s] or None).
AGAINST_CASES = (('step_0p1', 'controller_every_step', None),
                 ('step_0p1', 'controller_1khz', 1e-3),
                 ('sine_0p1_10pi', 'controller_every_step', None),
                 ('sine_0p1_10pi', 'controller_1khz', 1e-3))
#: What a tree's process runs (only ``simulate`` and ``default_params``, which every revision
#: has): argv = duration, repeat, cases as JSON; prints ``{case: best wall s}``.
_TIMER = '''
import json, sys
from eha_ros.physics import default_params, simulate
duration, repeat, cases = float(sys.argv[1]), int(sys.argv[2]), json.loads(sys.argv[3])
p = default_params()
out = {}
for scenario, label, period in cases:
    simulate(p, scenario, duration_s=2e-3, dt_s=1e-6, controller_period_s=period)  # compile
    out[scenario + '/' + label] = min(
        simulate(p, scenario, duration_s=duration, dt_s=1e-6,
                 controller_period_s=period).wall_time_s for _ in range(repeat))
print(json.dumps(out))
'''


def _time_tree(tree: Path, duration: float, repeat: int, cases) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), EHA_ROS_CONFIG_DIR=str(tree / 'config'),
               NUMBA_NUM_THREADS='1')
    r = subprocess.run([sys.executable, '-c', _TIMER, str(duration), str(repeat),
                        json.dumps(cases)], cwd=tree, env=env, capture_output=True, text=True)
    if r.returncode:
        last = (r.stderr.strip().splitlines() or [f'exit {r.returncode}'])[-1]
        sys.exit(f'plant_rtf: timing {tree} failed: {last}')
    return json.loads(r.stdout.strip().splitlines()[-1])


def against(rev: str, rounds: int, repeat: int, duration: float) -> dict:
    """This checkout against ``rev``, side by side (module docstring)."""
    try:
        sha = subprocess.run(['git', '-C', str(ROOT), 'rev-parse', '--verify',
                              f'{rev}^{{commit}}'], capture_output=True, text=True,
                             check=True).stdout.strip()
    except subprocess.CalledProcessError:
        sys.exit(f'plant_rtf: --against {rev}: not a revision of this repository')
    tmp = Path(tempfile.mkdtemp(prefix='eha-rtf-against-'))
    tree = tmp / 'tree'
    subprocess.run(['git', '-C', str(ROOT), 'worktree', 'add', '--detach', str(tree), sha],
                   capture_output=True, check=True)
    out = {'benchmark': 'plant_rtf_against', 'against': rev, 'against_commit': sha,
           'checkout_commit': subprocess.run(['git', '-C', str(ROOT), 'rev-parse', 'HEAD'],
                                             capture_output=True, text=True).stdout.strip(),
           'checkout_dirty': bool(subprocess.run(
               ['git', '-C', str(ROOT), 'status', '--porcelain', '--untracked-files=no'],
               capture_output=True, text=True).stdout.strip()),
           'dt_s': 1e-6, 'simulated_s': duration, 'repeat': repeat, 'rounds': [],
           'load_before': [round(v, 2) for v in os.getloadavg()]}
    cases = [list(c) for c in AGAINST_CASES]
    try:
        for k in range(rounds):
            # alternate which tree goes first, so neither always runs on a warmer machine
            order = (('checkout', ROOT), ('against', tree))[::1 if k % 2 == 0 else -1]
            out['rounds'].append({name: _time_tree(t, duration, repeat, cases)
                                  for name, t in order})
    finally:
        subprocess.run(['git', '-C', str(ROOT), 'worktree', 'remove', '--force', str(tree)],
                       capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)
    out['cases'] = {}
    for key in out['rounds'][0]['checkout']:
        now = min(r['checkout'][key] for r in out['rounds'])
        then = min(r['against'][key] for r in out['rounds'])
        out['cases'][key] = {'real_time_factor': round(duration / now, 2),
                             'real_time_factor_against': round(duration / then, 2),
                             'ratio': round(then / now, 3)}
    out['load_after'] = [round(v, 2) for v in os.getloadavg()]
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--duration', type=float, default=1.0)
    ap.add_argument('--repeat', type=int, default=3)
    ap.add_argument('--models', default=','.join(m for m in MODELS if m != 'hf'))
    ap.add_argument('--large-dts', default='2e-6,5e-6')
    ap.add_argument('--split-dts', default='1e-5,2e-5,2.5e-5',
                    help='steps [s] at which hf and the dynamic surrogates are timed with the '
                         'split integrator')
    ap.add_argument('--against', metavar='REV', default=None,
                    help='time hf of this checkout against git revision REV, side by side')
    ap.add_argument('--rounds', type=int, default=3, help='alternations with --against')
    ap.add_argument('--smoke', action='store_true',
                    help='the same code on a tiny case (10 ms, one repeat, dlut and lut): a check')
    args = ap.parse_args()
    if args.against is not None:
        if args.rounds < 1 or args.repeat < 1 or args.duration <= 0:
            ap.error('--rounds and --repeat must be at least 1 and --duration positive')
        if args.smoke:
            args.rounds, args.repeat, args.duration = 1, 1, 0.01
        print(json.dumps({**against(args.against, args.rounds, args.repeat, args.duration),
                          'smoke': args.smoke}))
        return
    if args.smoke:
        args.duration, args.repeat, args.large_dts, args.split_dts = 0.01, 1, '5e-6', '1e-5'
        if args.models == ap.get_default('models'):
            args.models = 'dlut,lut'  # one dynamic, one static: each model compiles anew
    p = default_params()
    t0 = time.perf_counter()
    simulate(p, 'step_0p1', duration_s=1e-3)
    simulate(p, 'step_0p1', duration_s=1e-3, controller_period_s=1e-3)
    warmup = time.perf_counter() - t0
    try:
        large = [float(v) for v in args.large_dts.split(',') if v]
        split = [float(v) for v in args.split_dts.split(',') if v]
    except ValueError as exc:
        ap.error(f'--large-dts / --split-dts: {exc}')
    if not all(dt > 0 for dt in large + split):
        ap.error('--large-dts and --split-dts must be positive steps in seconds')
    out = {'benchmark': 'plant_rtf', 'smoke': args.smoke,
           'load_avg_before': [round(v, 2) for v in os.getloadavg()],
           'dt_s': 1e-6, 'simulated_s': args.duration,
           'jit_warmup_s': round(warmup, 3), 'cpu': platform.processor() or platform.machine(),
           'cases': {}}
    for scenario in ('step_0p1', 'sine_0p1_10pi'):
        for label, period in (('controller_every_step', None), ('controller_1khz', 1e-3)):
            walls = []
            for _ in range(args.repeat):
                r = simulate(p, scenario, duration_s=args.duration, dt_s=1e-6,
                             controller_period_s=period)
                walls.append(r.wall_time_s)
            best = min(walls)
            out['cases'][f'{scenario}/{label}'] = {
                'wall_s': round(best, 5), 'real_time_factor': round(args.duration / best, 2),
                'ns_per_step': round(best / (args.duration / 1e-6) * 1e9, 1)}
    out['real_time_factor'] = out['cases']['step_0p1/controller_every_step']['real_time_factor']
    out['real_time_factor_1khz_controller'] = out['cases']['step_0p1/controller_1khz'][
        'real_time_factor']
    models = [m for m in args.models.split(',') if m]
    out['models'] = {}
    for model in ['hf'] + models:
        fluid = None if model == 'hf' else load_surrogate(model, p)
        dynamic = model == 'hf' or model in DYNAMIC_MODELS
        runs = [('explicit', 1e-6)] + [('explicit', dt) for dt in large if dynamic] + [
            ('split', dt) for dt in split if dynamic]
        for integrator, dt in runs:
            simulate(p, 'step_0p1', duration_s=2e-3, dt_s=dt, controller_period_s=1e-3,
                     fluid=fluid, integrator=integrator)  # compile
            row = {}
            for scenario in ('step_0p1', 'sine_0p1_10pi'):
                best = min(simulate(p, scenario, duration_s=args.duration, dt_s=dt,
                                    controller_period_s=1e-3, fluid=fluid,
                                    integrator=integrator).wall_time_s
                           for _ in range(args.repeat))
                row[scenario] = {'wall_s_per_simulated_s': round(best / args.duration, 5),
                                 'real_time_factor': round(args.duration / best, 2),
                                 'ns_per_step': round(best / (args.duration / dt) * 1e9, 1)}
            tag = '@split' if integrator == 'split' else ''
            out['models'][f'{model}{tag}@dt={dt:g}'] = row
    hf_cost = {sc: out['models']['hf@dt=1e-06'][sc]['wall_s_per_simulated_s']
               for sc in ('step_0p1', 'sine_0p1_10pi')}
    for name, row in out['models'].items():
        same = out['models']['hf' + name[name.index('@'):]]
        for sc, v in row.items():
            v['cost_vs_hf'] = round(v['wall_s_per_simulated_s'] / hf_cost[sc], 3)
            v['cost_vs_hf_same_step'] = round(
                v['wall_s_per_simulated_s'] / same[sc]['wall_s_per_simulated_s'], 3)
    out['load_avg_after'] = [round(v, 2) for v in os.getloadavg()]
    print(json.dumps(out))


if __name__ == '__main__':
    main()
