"""Fit a centralised critic Q offline on a fixed set of stage-2 episodes and score it (issue 36).

Is Q underfitting (learner settings), missing information (its input), or chasing a target too noisy for any fit?
Rows of 75 % of the episodes train Q(s, ·) by regression of Q(s, a_taken) to a target; the other 25 % score it:

- R² of Q(s, a) against the measured discounted joint return to the episode's end (held-out episodes);
- the counterfactual ranking COMA hands the actor: for cars nearly at rest (< 2 m/s) holding a negative
  acceleration, Q(+0.2) - Q(keep) (+0.2 is the only way such a car moves again), and the same for moving cars;
- confounding: the mean A2 per action taken against E[G | a] - E[G].

Inputs (``--input``): ``paper`` = the shipped critic's (global state, others' actions, own slot one-hot);
``own`` = paper + the own car's state row (speed, accel, distance, road, ...) at a fixed place;
``own_gaps`` = own + the own car's nearest cars ahead and behind on both lanes of its observation grid (gap and
relative speed). Targets (``--target``): ``mc`` (discounted joint return to the episode's end, γ ``--gamma``),
``mc_agent`` (to the agent's exit), ``td0`` (one-step SARSA with a soft target network, episode horizon).

    python experiments/stage2_critic/fit_critic.py runs/critic/idas_v.pt --input own_gaps --target mc
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from torch import nn

from idas_sumo.env.layout import ACCEL_SCALE_MPS2, GRID_CELLS, N_SCALARS, SPEED_SCALE_MPS
from idas_sumo.env.state_layout import STATE_FEATURES, STATE_SLOTS

KEEP, PLUS = 2, 4
EGO_CELL = GRID_CELLS // 2


def returns(b: dict, gamma: float, horizon: str) -> np.ndarray:
    own, team = b["next_row"].numpy(), b["team_next_row"].numpy()
    link = np.where(own >= 0, own, team) if horizon == "episode" else own
    joint = b["joint_reward"].numpy().astype(np.float64)
    g = np.zeros(len(link))
    for i in range(len(link) - 1, -1, -1):
        g[i] = joint[i] + (gamma * g[link[i]] if link[i] >= 0 else 0.0)
    return g


def grid_gaps(obs: torch.Tensor) -> torch.Tensor:
    """(B, 8): per lane (own, other), the nearest occupied cell ahead and behind the ego cell: its distance
    (fraction of the 100 m visibility, 1 when none) and the relative speed there (0 when none)."""
    out = []
    cells = torch.arange(GRID_CELLS, dtype=torch.float32)
    for lane in range(2):
        occ = obs[:, N_SCALARS + 2 * lane * GRID_CELLS : N_SCALARS + (2 * lane + 1) * GRID_CELLS] > 0
        rel = obs[:, N_SCALARS + (2 * lane + 1) * GRID_CELLS : N_SCALARS + (2 * lane + 2) * GRID_CELLS]
        for ahead in (True, False):
            side = (cells > EGO_CELL + 10) if ahead else (cells < EGO_CELL - 10)
            dist = torch.where(occ & side, (cells - EGO_CELL).abs(), torch.tensor(1e9))
            d, idx = dist.min(1)
            found = d < 1e8
            out.append(torch.where(found, d / EGO_CELL, torch.ones_like(d)))
            out.append(torch.where(found, rel.gather(1, idx.unsqueeze(1)).squeeze(1), torch.zeros_like(d)))
    return torch.stack(out, 1)


def features(b: dict, kind: str) -> torch.Tensor:
    state, others, slot = b["state"], b["others_actions"], b["slot"].long()
    parts = [state, others, nn.functional.one_hot(slot, STATE_SLOTS).float()]
    if kind in ("own", "own_gaps"):
        rows = state.view(-1, STATE_SLOTS, STATE_FEATURES)
        parts.append(rows[torch.arange(len(slot)), slot])
    if kind == "own_gaps":
        parts.append(grid_gaps(b["obs"]))
    return torch.cat(parts, 1)


def mlp(n_in: int, hidden: int, layers: int) -> nn.Module:
    mods: list[nn.Module] = []
    for i in range(layers):
        mods += [nn.Linear(n_in if i == 0 else hidden, hidden), nn.ReLU()]
    return nn.Sequential(*mods, nn.Linear(hidden, 7))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data", type=Path)
    p.add_argument("--input", choices=("paper", "own", "own_gaps"), default="paper")
    p.add_argument("--target", choices=("mc", "mc_agent", "td0"), default="mc")
    p.add_argument("--gamma", type=float, default=0.99)
    p.add_argument("--epochs", type=int, default=50)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--hidden", type=int, default=128)
    p.add_argument("--layers", type=int, default=2)
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    d = torch.load(args.data, weights_only=False)
    b, ep = d["batch"], d["episode"].numpy()
    g_ep = returns(b, args.gamma, "episode")
    x = features(b, args.input)
    mu, sd = x.mean(0), x.std(0) + 1e-6
    x = (x - mu) / sd
    n_ep = ep.max() + 1
    train = torch.from_numpy(ep % 4 != 3)
    test = ~train
    act = b["action"].long()
    net = mlp(x.shape[1], args.hidden, args.layers)
    target_net = mlp(x.shape[1], args.hidden, args.layers)
    target_net.load_state_dict(net.state_dict())
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    y_fixed = torch.from_numpy(
        returns(b, args.gamma, "agent" if args.target == "mc_agent" else "episode")
    ).float()
    own, team = b["next_row"].long(), b["team_next_row"].long()
    link = torch.where(own >= 0, own, team)
    r = b["joint_reward"].float()
    tr_idx = torch.nonzero(train).squeeze(1)
    for _epoch in range(args.epochs):
        if args.target == "td0":
            with torch.no_grad():
                qn = target_net(x).gather(1, act.unsqueeze(1)).squeeze(1)
                y = r + args.gamma * torch.where(link >= 0, qn[link.clamp(min=0)], torch.zeros_like(r))
        else:
            y = y_fixed
        perm = tr_idx[torch.randperm(len(tr_idx))]
        for s in range(0, len(perm), args.batch_size):
            i = perm[s : s + args.batch_size]
            q = net(x[i]).gather(1, act[i].unsqueeze(1)).squeeze(1)
            loss = 0.5 * (q - y[i]).pow(2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            if args.target == "td0":
                with torch.no_grad():
                    for tp, op in zip(target_net.parameters(), net.parameters(), strict=True):
                        tp.lerp_(op, 0.01)
    report(args, net, x, b, act, g_ep, y, train, test, n_ep)


def report(args, net, x, b, act, g_ep, y, train, test, n_ep) -> None:
    with torch.no_grad():
        q_all = net(x)
        probs = torch.softmax(torch.zeros_like(q_all), 1)  # placeholder replaced below
    mask = b["mask"].bool()
    # COMA's baseline uses the policy's probabilities; offline we weigh by the empirical policy: the taken
    # action's one-hot smoothed over allowed actions is not available, so use uniform over allowed actions.
    probs = mask.float() / mask.float().sum(1, keepdim=True)
    q_taken = q_all.gather(1, act.unsqueeze(1)).squeeze(1).numpy()
    g = g_ep
    yt = y.numpy()

    def r2(pred: np.ndarray, tgt: np.ndarray, rows: torch.Tensor) -> float:
        m = rows.numpy()
        return 1.0 - np.var(tgt[m] - pred[m]) / np.var(tgt[m])

    speed = b["obs"][:, 0].numpy() * SPEED_SCALE_MPS
    accel = b["obs"][:, 1].numpy() * ACCEL_SCALE_MPS2
    line = (
        f"{args.data.stem:14s} input {args.input:8s} target {args.target:8s} γ {args.gamma} ep {args.epochs:3d}"
        f" lr {args.lr:g} bs {args.batch_size} {args.layers}x{args.hidden}: R² train {r2(q_taken, yt, train):+.2f},"
        f" held-out vs own target {r2(q_taken, yt, test):+.2f}, vs G(episode) {r2(q_taken, g, test):+.2f}"
    )
    print(line)
    both = mask[:, PLUS] & mask[:, KEEP]
    for name, rows in (
        ("at rest, a < 0", (speed < 2.0) & (accel < 0)),
        ("moving", speed >= 2.0),
    ):
        m = torch.from_numpy(rows) & both & test
        if not m.any():
            continue
        diff = (q_all[m, PLUS] - q_all[m, KEEP]).numpy()
        print(
            f"    {name:15s} n {int(m.sum()):6d}: Q(+0.2) - Q(keep) mean {diff.mean():+.3f},"
            f" +0.2 ranked above keep in {np.mean(diff > 0):.0%}"
        )
    baseline = (q_all * probs).sum(1).numpy()
    a2 = q_taken - baseline
    m = test.numpy()
    a = act.numpy()
    rest = (speed < 2.0) & (accel < 0)
    for name, rows in (("at rest, a < 0", m & rest), ("all", m)):
        if not rows.any():
            continue
        print(
            f"    {name:15s} A2 = Q(s,a) - b, keep / +0.2: "
            f"{a2[rows & (a == KEEP)].mean():+.2f} / {a2[rows & (a == PLUS)].mean():+.2f};"
            f" A2 = G - b: {(g - baseline)[rows & (a == KEEP)].mean():+.2f} / {(g - baseline)[rows & (a == PLUS)].mean():+.2f}"
            f" (taken {int((rows & (a == KEEP)).sum())} / {int((rows & (a == PLUS)).sum())})"
        )
    print(
        "    held-out mean A2 per action taken "
        + " ".join(f"{a2[m & (a == k)].mean():+6.2f}" if (m & (a == k)).any() else "   nan" for k in range(7))
    )
    print(
        "    held-out E[G|a] - E[G]            "
        + " ".join(
            f"{g[m & (a == k)].mean() - g[m].mean():+6.2f}" if (m & (a == k)).any() else "   nan"
            for k in range(7)
        )
    )


if __name__ == "__main__":
    main()
