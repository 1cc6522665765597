#!/usr/bin/env python3
"""Peer for `mapless bench learner`: gradient updates per second of Stable-Baselines3's SAC, TD3
and DDPG on CPU, plus a CleanRL-style plain-PyTorch copy of the same updates, with the paper's
sizes (17-float observations, 2 actions in [-1, 1], 2x256 hidden, batch 128).

Run it through bench/run-sb3-peer.sh, which installs the pinned stable-baselines3 next to the
repository's torch. Directly:

    PYTHONPATH=bench/.sb3 .torch/venv/bin/python bench/sb3_peer.py [--seconds 5] [--threads 1 2]

What is timed, per (implementation, algorithm, thread count):
  * the replay buffer (SB3's `ReplayBuffer`, which CleanRL also uses) is pre-filled with
    `--buffer` random transitions before anything is timed;
  * updates run untimed for `--warmup` seconds (allocator, lazy initialisation, caches);
  * then whole calls of `model.train(gradient_steps=N, batch_size=128)` (SB3) or N iterations
    of CleanRL's update block run until `--seconds` of wall clock have passed (N = `--chunk`,
    by default chosen from the warm-up rate so that a call takes about 1/20 of the budget);
    updates/s = updates done / elapsed. Each update samples a minibatch from the buffer (numpy
    gather + copy into torch), as both libraries do in training.
Nothing else (no environment steps, no action selection for acting) is timed. Each line also
records the 1-minute load average before timing and `others_busy_cores`: how many cores the rest
of the machine kept busy during the timed window (from /proc/stat minus this process's CPU
time). On a shared machine, trust only lines where that is near 0; with 2 threads torch's OpenMP
workers slow down by orders of magnitude when another process takes one of 2 cores.

One "update" is one gradient step as the library counts it: one critic step, plus the actor
(and, for SAC, the entropy-coefficient) step when the algorithm's schedule says so, plus the
Polyak target update. Schedules are the libraries' own and are reported in each JSON line:
  * SB3 SAC: actor + alpha every step; SB3 TD3: actor every 2nd step (policy_delay=2);
    SB3 DDPG: actor every step (it is TD3 with policy_delay=1, one critic, no target noise).
  * CleanRL SAC: every 2nd step the actor+alpha step runs twice (policy_frequency=2, so on
    average once per step); CleanRL TD3 and DDPG: actor every 2nd step (policy_frequency=2, the
    defaults of td3_continuous_action.py and ddpg_continuous_action.py).

Hyper-parameters: gamma 0.995, tau 0.001 (the paper's). Learning rates do not change the cost of
an update, but for the record: SB3 has a single `learning_rate` for every optimiser (actor,
critics, entropy coefficient); we give it 5e-4 (the critic's). The CleanRL-style code has one
optimiser per network, so it uses actor 5e-5 / critic 5e-4 (and 5e-4 for alpha, as CleanRL uses
q_lr for alpha). SAC learns its entropy coefficient (SB3 ent_coef="auto", CleanRL autotune=True,
target entropy -2) in both.

Threads: torch.set_num_threads(T) and torch.set_num_interop_threads(T). The inter-op count can
be set only once per process, so the parent starts one child process per thread count (with
OMP/MKL/OpenBLAS thread variables also set to T) and relays its JSON lines.

Subnormal floats: by default the peer runs as its users do, with the CPU's IEEE default.
`--flush-denormal` calls torch.set_flush_denormal(True) first, which treats subnormal floats
as 0 on the calling thread; torch's OpenMP workers start later and inherit the mode, which the
worker checks with a probe product over all threads before it measures. It matters on Intel
CPUs, where each operation on a subnormal costs a microcode assist, and Adam's first moment of
a parameter with zero gradient (a dead ReLU unit) shrinks into the subnormal range and stays
there. mapless stores such moments as 0 (learner/src/optim.rs), so this flag is the
like-for-like setting for that; run-sb3-peer.sh passes it with PEER_FTZ=1.

Output: one JSON object per line on stdout, e.g.
  {"bench": "learner", "impl": "sb3", "algo": "sac", "threads": 1, "updates_per_s": 321.0, ...}
"""

import argparse
import json
import os
import subprocess
import sys
import time

OBS_DIM = 17
ACT_DIM = 2
HIDDEN = 256
BATCH = 128
GAMMA = 0.995
TAU = 0.001
ACTOR_LR = 5e-5
CRITIC_LR = 5e-4
SB3_LR = CRITIC_LR  # SB3: one learning rate for all optimisers


def parse_args():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=5.0, help="timed wall-clock seconds per measurement")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch thread counts (one process each)")
    p.add_argument("--algos", nargs="+", default=["sac", "td3", "ddpg"], choices=["sac", "td3", "ddpg"])
    p.add_argument("--impls", nargs="+", default=["sb3", "cleanrl"], choices=["sb3", "cleanrl"])
    p.add_argument("--buffer", type=int, default=100_000, help="replay transitions pre-filled (>= 10000)")
    p.add_argument("--warmup", type=float, default=1.0, help="untimed warm-up seconds before timing")
    p.add_argument(
        "--chunk", type=int, default=0, help="gradient steps per timed train() call, even; 0: about 1/20 of --seconds"
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--flush-denormal",
        action="store_true",
        help="torch.set_flush_denormal(True) first (subnormal floats read and written as 0 on every"
        " thread torch uses, checked by a probe); rows say flush_denormal",
    )
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)  # internal: thread count
    a = p.parse_args()
    if a.buffer < 10_000:
        p.error("--buffer must be >= 10000")
    if a.chunk < 0 or a.chunk % 2:
        p.error("--chunk must be even (the delayed actor updates then average out), or 0 for auto")
    return a


# --------------------------------------------------------------------------------------------
# Parent: one child process per thread count.


def run_parent(a):
    for t in a.threads:
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
            env[var] = str(t)
        argv = [sys.executable, os.path.abspath(__file__), "--worker", str(t)]
        argv += ["--seconds", str(a.seconds), "--algos", *a.algos, "--impls", *a.impls]
        argv += ["--buffer", str(a.buffer), "--warmup", str(a.warmup), "--chunk", str(a.chunk)]
        argv += ["--seed", str(a.seed)] + (["--flush-denormal"] if a.flush_denormal else [])
        # The child's stdout lines go straight through (flushed per line).
        rc = subprocess.run(argv, env=env).returncode
        if rc != 0:
            sys.exit(f"sb3_peer: worker for {t} thread(s) failed with exit status {rc}")


# --------------------------------------------------------------------------------------------
# Child: everything torch happens here.


def machine_busy_s():
    """CPU-seconds all cores have spent busy since boot (Linux /proc/stat), or None."""
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    # user nice system idle iowait irq softirq steal (guest time is already in user/nice)
    return (sum(v[:8]) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")


def own_cpu_s():
    t = os.times()
    return t.user + t.system


def run_worker(a):
    t = a.worker
    import torch

    torch.set_num_threads(t)
    torch.set_num_interop_threads(t)
    if a.flush_denormal:
        if not torch.set_flush_denormal(True):
            sys.exit("sb3_peer: --flush-denormal: this CPU has no flush-to-zero mode")
        # The mode is per thread; OpenMP's workers, started by this first parallel product,
        # inherit it. A subnormal product anywhere in this 4M-element tensor means one did not.
        kept = (torch.full((1 << 22,), 1e-30) * 1e-10).count_nonzero().item()
        if kept:
            sys.exit(f"sb3_peer: --flush-denormal: {kept} subnormal products kept; not every thread flushes")

    import gymnasium as gym
    import numpy as np
    import stable_baselines3

    obs_space = gym.spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float32)
    act_space = gym.spaces.Box(-1.0, 1.0, shape=(ACT_DIM,), dtype=np.float32)
    rng = np.random.default_rng(a.seed)

    def fill(rb):
        """Random transitions, written straight into the buffer's arrays (n_envs = 1)."""
        n = a.buffer
        rb.observations[:n] = rng.standard_normal((n, 1, OBS_DIM), dtype=np.float32)
        rb.next_observations[:n] = rng.standard_normal((n, 1, OBS_DIM), dtype=np.float32)
        rb.actions[:n] = rng.uniform(-1.0, 1.0, (n, 1, ACT_DIM)).astype(np.float32)
        rb.rewards[:n] = rng.standard_normal((n, 1), dtype=np.float32)
        rb.dones[:n] = (rng.random((n, 1)) < 0.01).astype(np.float32)
        rb.pos = n % rb.buffer_size
        rb.full = n >= rb.buffer_size

    common = {
        "bench": "learner",
        "threads": t,
        "batch": BATCH,
        "hidden": HIDDEN,
        "obs_dim": OBS_DIM,
        "act_dim": ACT_DIM,
        "device": "cpu",
        "torch": torch.__version__.split("+")[0],
        "sb3": stable_baselines3.__version__,
        "python": "%d.%d.%d" % sys.version_info[:3],
        "buffer": a.buffer,
        "flush_denormal": a.flush_denormal,
    }

    def measure(step_chunk, extra):
        """step_chunk(n) runs n updates (n even). Warm up for a.warmup seconds, pick the chunk
        size, then time whole chunks until a.seconds have passed."""
        done, t0 = 0, time.perf_counter()
        while True:
            step_chunk(2)
            done += 2
            warm = time.perf_counter() - t0
            if warm >= a.warmup:
                break
        chunk = a.chunk or min(256, max(2, 2 * round(done / warm * a.seconds / 40)))
        load1 = os.getloadavg()[0]
        busy0, own0 = machine_busy_s(), own_cpu_s()
        updates = 0
        t0 = time.perf_counter()
        deadline = t0 + a.seconds
        while True:
            step_chunk(chunk)
            updates += chunk
            now = time.perf_counter()
            if now >= deadline:
                break
        elapsed = now - t0
        busy1, own1 = machine_busy_s(), own_cpu_s()
        row = dict(common)
        row.update(extra)
        row.update(
            {
                "updates_per_s": round(updates / elapsed, 1),
                "updates": updates,
                "seconds": round(elapsed, 3),
                "chunk": chunk,
                "torch_threads": torch.get_num_threads(),
                "load1_before": round(load1, 2),
                "cpus": os.cpu_count(),
            }
        )
        if busy0 is not None and busy1 is not None:
            # Cores kept busy by everything else on the machine while we were timed.
            row["others_busy_cores"] = round(max(0.0, (busy1 - busy0) - (own1 - own0)) / elapsed, 2)
        row["own_cores"] = round((own1 - own0) / elapsed, 2)  # CPU this process got (all its threads)
        print(json.dumps(row), flush=True)

    for impl in a.impls:
        for algo in a.algos:
            torch.manual_seed(a.seed)
            np.random.seed(a.seed)
            if impl == "sb3":
                step_chunk, extra = make_sb3(algo, obs_space, act_space, fill, a)
            else:
                step_chunk, extra = make_cleanrl(algo, obs_space, act_space, fill, a)
            measure(step_chunk, {"impl": impl, "algo": algo, **extra})


# --------------------------------------------------------------------------------------------
# Stable-Baselines3: the library's own `train()`.


def make_sb3(algo, obs_space, act_space, fill, a):
    import gymnasium as gym
    import numpy as np
    from stable_baselines3 import DDPG, SAC, TD3
    from stable_baselines3.common.logger import Logger

    class SpacesOnly(gym.Env):
        """Gives SB3 the spaces; never stepped (only train() is timed)."""

        observation_space = obs_space
        action_space = act_space

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            return np.zeros(OBS_DIM, dtype=np.float32), {}

        def step(self, action):
            return np.zeros(OBS_DIM, dtype=np.float32), 0.0, False, False, {}

    kwargs = dict(
        learning_rate=SB3_LR,
        buffer_size=a.buffer,
        learning_starts=0,
        batch_size=BATCH,
        tau=TAU,
        gamma=GAMMA,
        policy_kwargs=dict(net_arch=dict(pi=[HIDDEN, HIDDEN], qf=[HIDDEN, HIDDEN])),
        device="cpu",
        seed=a.seed,
        verbose=0,
    )
    cls = {"sac": SAC, "td3": TD3, "ddpg": DDPG}[algo]
    model = cls("MlpPolicy", SpacesOnly(), **kwargs)
    # train() logs through model.logger, which learn() would set up; give it one with no outputs.
    model.set_logger(Logger(folder=None, output_formats=[]))
    fill(model.replay_buffer)

    def step_chunk(n):
        model.train(gradient_steps=n, batch_size=BATCH)

    extra = {"lr": SB3_LR, "gamma": GAMMA, "tau": TAU, "n_critics": model.policy_kwargs.get("n_critics", 2)}
    if algo == "sac":
        extra["ent_coef"] = "auto"
    else:
        extra["policy_delay"] = model.policy_delay
    return step_chunk, extra


# --------------------------------------------------------------------------------------------
# CleanRL-style: the update blocks of CleanRL's single-file scripts, copied (comments, logging
# and the environment loop dropped; `args.*` replaced by the constants above; `global_step`
# counts updates). Source: https://github.com/vwxyzjn/cleanrl, files
#   cleanrl/sac_continuous_action.py   (SoftQNetwork, Actor, LOG_STD_*, "ALGO LOGIC: training")
#   cleanrl/td3_continuous_action.py   (QNetwork, Actor, training block)
#   cleanrl/ddpg_continuous_action.py  (QNetwork, Actor, training block)
# as of commit 004f8a086a892a2a180f4dd332b90d83a968aa7a. CleanRL samples from cleanrl_utils'
# ReplayBuffer, an adapted copy of SB3's ReplayBuffer; SB3's is used here.


def make_cleanrl(algo, obs_space, act_space, fill, a):
    import numpy as np
    import torch
    import torch.nn as nn
    import torch.nn.functional as F
    import torch.optim as optim
    from stable_baselines3.common.buffers import ReplayBuffer

    device = torch.device("cpu")

    class Envs:  # what the networks read from CleanRL's `envs`
        single_observation_space = obs_space
        single_action_space = act_space

    envs = Envs()

    class SoftQNetwork(nn.Module):  # also CleanRL's QNetwork in td3/ddpg (identical)
        def __init__(self, env):
            super().__init__()
            self.fc1 = nn.Linear(
                np.array(env.single_observation_space.shape).prod() + np.prod(env.single_action_space.shape),
                HIDDEN,
            )
            self.fc2 = nn.Linear(HIDDEN, HIDDEN)
            self.fc3 = nn.Linear(HIDDEN, 1)

        def forward(self, x, a):
            x = torch.cat([x, a], 1)
            x = F.relu(self.fc1(x))
            x = F.relu(self.fc2(x))
            x = self.fc3(x)
            return x

    LOG_STD_MAX = 2
    LOG_STD_MIN = -5

    def scale_bias(module, env):
        module.register_buffer(
            "action_scale",
            torch.tensor((env.single_action_space.high - env.single_action_space.low) / 2.0, dtype=torch.float32),
        )
        module.register_buffer(
            "action_bias",
            torch.tensor((env.single_action_space.high + env.single_action_space.low) / 2.0, dtype=torch.float32),
        )

    class SacActor(nn.Module):
        def __init__(self, env):
            super().__init__()
            self.fc1 = nn.Linear(np.array(env.single_observation_space.shape).prod(), HIDDEN)
            self.fc2 = nn.Linear(HIDDEN, HIDDEN)
            self.fc_mean = nn.Linear(HIDDEN, np.prod(env.single_action_space.shape))
            self.fc_logstd = nn.Linear(HIDDEN, np.prod(env.single_action_space.shape))
            scale_bias(self, env)

        def forward(self, x):
            x = F.relu(self.fc1(x))
            x = F.relu(self.fc2(x))
            mean = self.fc_mean(x)
            log_std = self.fc_logstd(x)
            log_std = torch.tanh(log_std)
            log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (log_std + 1)
            return mean, log_std

        def get_action(self, x):
            mean, log_std = self(x)
            std = log_std.exp()
            normal = torch.distributions.Normal(mean, std)
            x_t = normal.rsample()
            y_t = torch.tanh(x_t)
            action = y_t * self.action_scale + self.action_bias
            log_prob = normal.log_prob(x_t)
            log_prob -= torch.log(self.action_scale * (1 - y_t.pow(2)) + 1e-6)
            log_prob = log_prob.sum(1, keepdim=True)
            mean = torch.tanh(mean) * self.action_scale + self.action_bias
            return action, log_prob, mean

    class DetActor(nn.Module):  # td3/ddpg Actor
        def __init__(self, env):
            super().__init__()
            self.fc1 = nn.Linear(np.array(env.single_observation_space.shape).prod(), HIDDEN)
            self.fc2 = nn.Linear(HIDDEN, HIDDEN)
            self.fc_mu = nn.Linear(HIDDEN, np.prod(env.single_action_space.shape))
            scale_bias(self, env)

        def forward(self, x):
            x = F.relu(self.fc1(x))
            x = F.relu(self.fc2(x))
            x = torch.tanh(self.fc_mu(x))
            return x * self.action_scale + self.action_bias

    rb = ReplayBuffer(a.buffer, obs_space, act_space, device, n_envs=1, handle_timeout_termination=False)
    fill(rb)
    policy_frequency = 2  # CleanRL's default in all three scripts
    target_network_frequency = 1  # sac only
    policy_noise, noise_clip = 0.2, 0.5  # td3 only
    state = {"global_step": 0}

    if algo == "sac":
        actor = SacActor(envs).to(device)
        qf1 = SoftQNetwork(envs).to(device)
        qf2 = SoftQNetwork(envs).to(device)
        qf1_target = SoftQNetwork(envs).to(device)
        qf2_target = SoftQNetwork(envs).to(device)
        qf1_target.load_state_dict(qf1.state_dict())
        qf2_target.load_state_dict(qf2.state_dict())
        q_optimizer = optim.Adam(list(qf1.parameters()) + list(qf2.parameters()), lr=CRITIC_LR)
        actor_optimizer = optim.Adam(list(actor.parameters()), lr=ACTOR_LR)
        target_entropy = -torch.prod(torch.Tensor(envs.single_action_space.shape).to(device)).item()
        log_alpha = torch.zeros(1, requires_grad=True, device=device)
        state["alpha"] = log_alpha.exp().item()
        a_optimizer = optim.Adam([log_alpha], lr=CRITIC_LR)

        def update():
            global_step, alpha = state["global_step"], state["alpha"]
            data = rb.sample(BATCH)
            with torch.no_grad():
                next_state_actions, next_state_log_pi, _ = actor.get_action(data.next_observations)
                qf1_next_target = qf1_target(data.next_observations, next_state_actions)
                qf2_next_target = qf2_target(data.next_observations, next_state_actions)
                min_qf_next_target = torch.min(qf1_next_target, qf2_next_target) - alpha * next_state_log_pi
                next_q_value = data.rewards.flatten() + (1 - data.dones.flatten()) * GAMMA * (min_qf_next_target).view(-1)

            qf1_a_values = qf1(data.observations, data.actions).view(-1)
            qf2_a_values = qf2(data.observations, data.actions).view(-1)
            qf1_loss = F.mse_loss(qf1_a_values, next_q_value)
            qf2_loss = F.mse_loss(qf2_a_values, next_q_value)
            qf_loss = qf1_loss + qf2_loss

            q_optimizer.zero_grad()
            qf_loss.backward()
            q_optimizer.step()

            if global_step % policy_frequency == 0:
                for _ in range(policy_frequency):
                    pi, log_pi, _ = actor.get_action(data.observations)
                    qf1_pi = qf1(data.observations, pi)
                    qf2_pi = qf2(data.observations, pi)
                    min_qf_pi = torch.min(qf1_pi, qf2_pi)
                    actor_loss = ((alpha * log_pi) - min_qf_pi).mean()

                    actor_optimizer.zero_grad()
                    actor_loss.backward()
                    actor_optimizer.step()

                    with torch.no_grad():
                        _, log_pi, _ = actor.get_action(data.observations)
                    alpha_loss = (-log_alpha.exp() * (log_pi + target_entropy)).mean()

                    a_optimizer.zero_grad()
                    alpha_loss.backward()
                    a_optimizer.step()
                    alpha = log_alpha.exp().item()

            if global_step % target_network_frequency == 0:
                for param, target_param in zip(qf1.parameters(), qf1_target.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
                for param, target_param in zip(qf2.parameters(), qf2_target.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
            state["global_step"], state["alpha"] = global_step + 1, alpha

        extra = {"autotune": True, "policy_frequency": policy_frequency, "n_critics": 2}

    else:  # td3, ddpg
        two = algo == "td3"
        actor = DetActor(envs).to(device)
        qf1 = SoftQNetwork(envs).to(device)
        qf1_target = SoftQNetwork(envs).to(device)
        target_actor = DetActor(envs).to(device)
        target_actor.load_state_dict(actor.state_dict())
        qf1_target.load_state_dict(qf1.state_dict())
        if two:
            qf2 = SoftQNetwork(envs).to(device)
            qf2_target = SoftQNetwork(envs).to(device)
            qf2_target.load_state_dict(qf2.state_dict())
            q_optimizer = optim.Adam(list(qf1.parameters()) + list(qf2.parameters()), lr=CRITIC_LR)
        else:
            q_optimizer = optim.Adam(list(qf1.parameters()), lr=CRITIC_LR)
        actor_optimizer = optim.Adam(list(actor.parameters()), lr=ACTOR_LR)

        def update_td3():
            global_step = state["global_step"]
            data = rb.sample(BATCH)
            with torch.no_grad():
                clipped_noise = (torch.randn_like(data.actions, device=device) * policy_noise).clamp(
                    -noise_clip, noise_clip
                ) * target_actor.action_scale

                next_state_actions = (target_actor(data.next_observations) + clipped_noise).clamp(
                    envs.single_action_space.low[0], envs.single_action_space.high[0]
                )
                qf1_next_target = qf1_target(data.next_observations, next_state_actions)
                qf2_next_target = qf2_target(data.next_observations, next_state_actions)
                min_qf_next_target = torch.min(qf1_next_target, qf2_next_target)
                next_q_value = data.rewards.flatten() + (1 - data.dones.flatten()) * GAMMA * (min_qf_next_target).view(-1)

            qf1_a_values = qf1(data.observations, data.actions).view(-1)
            qf2_a_values = qf2(data.observations, data.actions).view(-1)
            qf1_loss = F.mse_loss(qf1_a_values, next_q_value)
            qf2_loss = F.mse_loss(qf2_a_values, next_q_value)
            qf_loss = qf1_loss + qf2_loss

            q_optimizer.zero_grad()
            qf_loss.backward()
            q_optimizer.step()

            if global_step % policy_frequency == 0:
                actor_loss = -qf1(data.observations, actor(data.observations)).mean()
                actor_optimizer.zero_grad()
                actor_loss.backward()
                actor_optimizer.step()

                for param, target_param in zip(actor.parameters(), target_actor.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
                for param, target_param in zip(qf1.parameters(), qf1_target.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
                for param, target_param in zip(qf2.parameters(), qf2_target.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
            state["global_step"] = global_step + 1

        def update_ddpg():
            global_step = state["global_step"]
            data = rb.sample(BATCH)
            with torch.no_grad():
                next_state_actions = target_actor(data.next_observations)
                qf1_next_target = qf1_target(data.next_observations, next_state_actions)
                next_q_value = data.rewards.flatten() + (1 - data.dones.flatten()) * GAMMA * (qf1_next_target).view(-1)

            qf1_a_values = qf1(data.observations, data.actions).view(-1)
            qf1_loss = F.mse_loss(qf1_a_values, next_q_value)

            q_optimizer.zero_grad()
            qf1_loss.backward()
            q_optimizer.step()

            if global_step % policy_frequency == 0:
                actor_loss = -qf1(data.observations, actor(data.observations)).mean()
                actor_optimizer.zero_grad()
                actor_loss.backward()
                actor_optimizer.step()

                for param, target_param in zip(actor.parameters(), target_actor.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
                for param, target_param in zip(qf1.parameters(), qf1_target.parameters()):
                    target_param.data.copy_(TAU * param.data + (1 - TAU) * target_param.data)
            state["global_step"] = global_step + 1

        update = update_td3 if two else update_ddpg
        extra = {"policy_frequency": policy_frequency, "n_critics": 2 if two else 1}

    def step_chunk(n):
        for _ in range(n):
            update()

    extra.update({"actor_lr": ACTOR_LR, "critic_lr": CRITIC_LR, "gamma": GAMMA, "tau": TAU})
    return step_chunk, extra


def main():
    a = parse_args()
    if a.worker is None:
        run_parent(a)
    else:
        run_worker(a)


if __name__ == "__main__":
    main()
