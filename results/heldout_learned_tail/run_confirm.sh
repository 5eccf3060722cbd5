#!/usr/bin/env bash
# One lane of the learned-tail confirmation: for each "<name> <seed>" argument pair, train
# the row (RESULTS.md's table) from this worktree, evaluate its final policy on 100
# deterministic test episodes and archive its records into ARCHIVE (no checkpoints).
#   ARCHIVE=/path/to/main/results/heldout_learned_tail/runs \
#     nohup results/heldout_learned_tail/run_confirm.sh wcsac_prestudy_0.1 110 sac_lag 110 &
set -euo pipefail
: "${ARCHIVE:?set ARCHIVE to the runs/ folder of this study in the main checkout}"
export OMP_NUM_THREADS=1 MUJOCO_GL=egl
PY=.venv/bin/python

overrides() {
  case "$1" in
    sac_lag) echo "algo=sac_lag" ;;
    wcsac_prestudy_0.1) echo "algo=wcsac risk_level=0.1 algo.safety_critic=gaussian algo.variance_loss=glm algo.variance_target=td algo.kappa_signal=critic algo.kappa_lr_scale=1.0 algo.alpha_init=1.0 algo.actor_lr=null algo.label=$1" ;;
    *) echo "unknown row: $1" >&2; return 1 ;;
  esac
}

while [ $# -ge 2 ]; do
  name=$1 seed=$2; shift 2
  run=multirun/heldout_learned_tail/${name}_static_seed${seed}
  # shellcheck disable=SC2046
  $PY train.py experiment=evidence_static hydra.mode=RUN $(overrides "$name") \
    seed="$seed" hydra.run.dir="$run" keep_checkpoints_at='[1,10,20]' progress_bar=false
  $PY -m wcsac_rl.evaluate "$run" --episodes 100 --archive "$ARCHIVE" --no-progress
  echo "$(date -u +%FT%TZ) done $name $seed"
done
