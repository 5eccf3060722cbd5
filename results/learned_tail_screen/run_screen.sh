#!/usr/bin/env bash
# One lane of the learned-tail screen: for each "<name> <seed>" argument pair, train the
# recipe (RESULTS.md's table) from this worktree, evaluate its final policy on 100
# deterministic test episodes and archive its records into ARCHIVE (no checkpoints).
#   ARCHIVE=/path/to/main/results/learned_tail_screen/runs \
#     nohup results/learned_tail_screen/run_screen.sh wcsac_prestudy_0.1 0 wcsac_prestudy_0.1 1 &
set -euo pipefail
: "${ARCHIVE:?set ARCHIVE to the runs/ folder of this study in the main checkout}"
export OMP_NUM_THREADS=1 MUJOCO_GL=egl
PY=.venv/bin/python

overrides() {
  case "$1" in
    wcsac_prestudy_0.1) echo "algo=wcsac algo.safety_critic=gaussian algo.kappa_signal=critic algo.kappa_lr_scale=1.0 algo.alpha_init=1.0 algo.actor_lr=null algo.label=$1" ;;
    wcsac_paper_0.1) echo "algo=wcsac_paper" ;;
    wcsac_hold_0.1) echo "algo=wcsac algo.kappa_hold_goal_rate=0.9 algo.label=$1" ;;
    wcsac_window_mean_0.1) echo "algo=wcsac algo.kappa_episode_statistic=mean algo.label=$1" ;;
    *) echo "unknown recipe: $1" >&2; return 1 ;;
  esac
}

while [ $# -ge 2 ]; do
  name=$1 seed=$2; shift 2
  run=multirun/learned_tail_screen/${name}_static_seed${seed}
  # shellcheck disable=SC2046
  $PY train.py experiment=evidence_static hydra.mode=RUN $(overrides "$name") risk_level=0.1 \
    seed="$seed" hydra.run.dir="$run" keep_checkpoints_at='[1,10,20]' progress_bar=false
  $PY -m wcsac_rl.evaluate "$run" --episodes 100 --archive "$ARCHIVE" --no-progress
  echo "$(date -u +%FT%TZ) done $name $seed"
done
