"""The safety critic, the reward critic and κ of a WCSAC checkpoint over robot positions.

The diagnostic behind the sixth round of results/training_safety/RESULTS.md (StaticEnv:
one hazard of radius 0.7 at the origin, the goal of radius 0.3 at (1.1, 1.1)).

Usage (from the repository root, the run's commit checked out)::

    OMP_NUM_THREADS=1 python results/training_safety/tools/gamma_map.py RUN_DIR OUT_PREFIX

It rebuilds the run the way ``OffPolicyTrainer.restore_policy`` does (``read_checkpoint``,
then ``builders.make_eval_env`` / ``make_agent`` / ``make_loss`` and
``load_module_state``) but keeps the loss, so that its safety head (Γ) and critics can be
read. At each position the robot is placed at rest with ``reset(options={"layout": ...})``,
heading at the goal, and a = π(s) is the deterministic action. Printed: maps of Γ, of
the critic's standard deviation (the Gaussian head's √V^c; for an IQN head the spread
of its quantiles) and of Q^r (the smaller twin); Γ, Q^c, the std and Q^r along the
diagonal from (2, 2) through the goal to the hazard's edge and along the circle through
the goal around the hazard; the forward-action gradients of Q^r and κΓ; and the goal
against points 0.5 further out. The arrays go to OUT_PREFIX.npz. It reads two of the
loss's private methods (``_critic_values``, ``_detached_critics``): a study tool pinned
to the commit of the runs it maps (ee73765), not an API.

Caveat, measured afterwards (RESULTS.md, seventh round; ``visited_reads.py``): a robot at
rest is not what the replay buffer holds, and the critics extrapolate there. At the
states really visited, Γ can differ from these maps several-fold either way. Near the
goal the Gaussian head's at-rest read is 1.7–10× its visited read. In the hazard the
IQN head's at-rest read is up to 20× below its visited read (1.1–20× on four
checkpoints). Read the maps as the critic's
shape at rest, not as the values the actor trains on.
"""

from __future__ import annotations

import math
import sys

import numpy as np
import torch
from omegaconf import OmegaConf
from torchrl.envs.utils import ExplorationType, set_exploration_type

from wcsac_rl.modules.tanh_normal import TanhNormalPolicy
from wcsac_rl.training import builders
from wcsac_rl.training.checkpoint import find_checkpoint, load_module_state, read_checkpoint
from wcsac_rl.training.devices import on_cpu
from wcsac_rl.training.trainer import env_max_episode_steps

torch.set_num_threads(1)
GOAL = np.array([1.1, 1.1])
HAZ = np.array([0.0, 0.0])


def rebuild(run_dir):
    path = find_checkpoint(run_dir)
    ckpt, _ = read_checkpoint(path)  # safe_load.load_data (weights_only)
    cfg = on_cpu(OmegaConf.create(ckpt["config"]))
    env = builders.make_eval_env(cfg, seed=0)
    agent = builders.make_agent(cfg, env)
    loss = builders.make_loss(cfg, agent, env_max_episode_steps(cfg))
    load_module_state(loss, ckpt["learner"].get("loss"))  # actor shares these params
    loss.eval()
    policy = TanhNormalPolicy(agent.actor).eval()
    return cfg, ckpt, env, loss, policy


def observe(env, pts):
    obs = []
    for p in pts:
        d = GOAL - p
        if np.hypot(*d) < 1e-6:  # at the goal: keep heading along the (2,2)->hazard line
            d = HAZ - GOAL
        lay = {"robot_xy": [float(p[0]), float(p[1])], "robot_heading": math.atan2(d[1], d[0])}
        td = env.reset(options={"layout": lay})
        obs.append(td["observation"].reshape(-1).clone())
    return torch.stack(obs)


def evaluate(loss, policy, obs, grads=False):
    from tensordict import TensorDict

    td = TensorDict({"observation": obs}, batch_size=[obs.shape[0]])
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        action = policy(td.clone())["action"]
    kappa = float(loss.kappa)
    action = action.detach().requires_grad_(grads)
    with torch.set_grad_enabled(grads):
        vals = loss._critic_values(td, action, loss._detached_critics())
        qr = vals.qvalue.min(0)[0]
        s = vals.safety
        gamma = loss.safety_head.cvar(s)  # the loss's own Gamma (nonnegative_cost etc.)
    out = {
        "action": action.detach().numpy(),
        "mean": s.mean.detach().numpy(),
        "std": s.variance.detach().sqrt().numpy() if s.variance is not None else np.zeros(len(obs)),
        "gamma": gamma.detach().numpy(),
        "qr": qr.detach().numpy(),
    }
    out["kg_minus_qr"] = kappa * out["gamma"] - out["qr"]
    if grads:
        gq = torch.autograd.grad(qr.sum(), action, retain_graph=True)[0]
        gg = torch.autograd.grad(gamma.sum(), action)[0]
        out["dqr_da"], out["kdg_da"] = gq.numpy(), kappa * gg.numpy()
    return out, kappa


def main(run_dir, prefix):
    cfg, ckpt, env, loss, policy = rebuild(run_dir)
    head = loss.safety_head
    print(
        f"run {run_dir}: frames {ckpt['frames']} seed {cfg.seed} cost_limit {cfg.cost_limit} "
        f"alpha {head.risk_level} nonneg {head.nonnegative_cost} head {head.kind} "
        f"cvar_mult {getattr(head, 'cvar_multiplier', float('nan')):.4f} threshold {float(loss.cost_threshold):.3f}"
    )
    # --- grid
    xs = np.round(np.arange(-2.0, 2.5 + 1e-9, 0.1), 2)
    X, Y = np.meshgrid(xs, xs)  # [iy, ix]
    pts = np.stack([X.ravel(), Y.ravel()], 1)
    g, kappa = evaluate(loss, policy, observe(env, pts))
    print(f"kappa {kappa:.4f}")
    res = {f"grid_{k}": v.reshape(X.shape + v.shape[1:]) for k, v in g.items()}
    res.update(xs=xs, kappa=kappa)
    # --- line (a): (2,2) -> goal -> hazard edge along the diagonal
    edge = 0.7 / math.sqrt(2)
    ta = np.round(np.arange(2.0, edge - 1e-9, -0.05), 3)
    ta = np.unique(np.concatenate([ta, [1.1, edge]]))[::-1]
    pa = np.stack([ta, ta], 1)
    la, _ = evaluate(loss, policy, observe(env, pa), grads=True)
    # --- line (b): circle r=1.56 about the hazard
    ang = np.arange(0, 361, 15)
    pb = 1.56 * np.stack([np.cos(np.radians(ang)), np.sin(np.radians(ang))], 1)
    lb, _ = evaluate(loss, policy, observe(env, pb), grads=True)
    # --- goal vs 0.5 further out (radial = diagonal, +x, +y)
    pc = np.array(
        [GOAL, GOAL + 0.5 / math.sqrt(2), GOAL + np.array([0.5, 0.0]), GOAL + np.array([0.0, 0.5])]
    )
    lc, _ = evaluate(loss, policy, observe(env, pc), grads=True)
    for k, v in la.items():
        res[f"lineA_{k}"] = v
    for k, v in lb.items():
        res[f"lineB_{k}"] = v
    for k, v in lc.items():
        res[f"cmp_{k}"] = v
    res.update(lineA_xy=pa, lineB_xy=pb, lineB_deg=ang, cmp_xy=pc)
    np.savez(f"{prefix}.npz", **res)

    np.set_printoptions(linewidth=250)
    step = 3  # text maps every 0.3
    idx = np.arange(0, len(xs), step)
    for name in ("gamma", "std", "qr"):
        m = res[f"grid_{name}"]
        print(
            f"\n{name} map (rows y from {xs[idx[-1]]} down, cols x {xs[idx[0]]}..{xs[idx[-1]]} step 0.3)"
        )
        print("      " + " ".join(f"{x:5.1f}" for x in xs[idx]))
        for iy in idx[::-1]:
            print(f"{xs[iy]:5.1f} " + " ".join(f"{m[iy, ix]:5.1f}" for ix in idx))

    def prof(title, labels, d):
        print(f"\n{title}  (kappa={kappa:.3f}; dQr/dfwd, k*dG/dfwd = grads wrt forward action)")
        print(" where      Gamma   mean    std  std%    Qr  kG-Qr   a_fwd a_turn dQr/df kdG/df")
        for lab, i in zip(labels, range(len(labels))):
            gm, mn, sd = d["gamma"][i], d["mean"][i], d["std"][i]
            sp = (
                100 * getattr(head, "cvar_multiplier", float("nan")) * sd / gm
                if gm > 1e-9
                else float("nan")
            )
            print(
                f"{lab:>9s} {gm:7.2f} {mn:6.2f} {sd:6.2f} {sp:4.0f}% {d['qr'][i]:6.2f} "
                f"{d['kg_minus_qr'][i]:6.2f} {d['action'][i, 0]:+.2f} {d['action'][i, 1]:+.2f} "
                f"{d['dqr_da'][i, 0]:+6.2f} {d['kdg_da'][i, 0]:+6.2f}"
            )

    prof(
        "Line (a) diagonal (x=y) from (2,2) to goal to hazard edge; label = x",
        [f"{t:.3f}" + ("G" if abs(t - 1.1) < 1e-9 else "") for t in ta],
        la,
    )
    prof(
        "Line (b) circle r=1.56 about hazard; label = angle deg (goal at 45)",
        [f"{a:d}" for a in ang],
        lb,
    )
    prof("Goal vs 0.5 further out", ["goal", "diag+0.5", "x+0.5", "y+0.5"], lc)
    for j, lab in enumerate(["diag", "x", "y"], 1):
        kdG = kappa * (lc["gamma"][j] - lc["gamma"][0])
        dQ = lc["qr"][j] - lc["qr"][0]
        print(
            f"  out({lab})-goal: k*dGamma {kdG:+.2f}  dQr {dQ:+.2f}  "
            f"d(Qr-kG) {dQ - kdG:+.2f} ({'out preferred' if dQ - kdG > 0 else 'goal preferred'})"
        )
    env.close()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
