#!/usr/bin/env bash
# One prepared GPU session (device machine: JAX 0.11.2 + CUDA preinstalled, no internet).
# Carried wheels in .whl/ (cp312): klimits, mujoco, mujoco-core, mujoco-mjx, brax and brax's
# missing pure-Python deps; see README "GPU". Logs go to $OUT (or ./gpu_out).
# SMALL=1 runs the same steps with tiny sizes (a dry run on the CPU).
set -u
OUT=${OUT:-gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ -d .whl ] && ! python3 -c "import brax, klimits" 2>/dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
if [ "${SMALL:-0}" = 1 ]; then B=64; BL=256; TS=40000; E=64; BS=32; T1=120; T2=120
else B=2048; BL=4096; TS=3000000; E=4096; BS=512; T1=${T1:-200}; T2=${T2:-0}; fi
run() { local name=$1 limit=$2; shift 2; echo "=== $name ($(date +%T), limit ${limit}s)";
  timeout "$limit" "$@" 2>&1 | grep -v "import warp\|import mujoco_warp" | tee "$OUT/$name.log"; }
# BALANCE=1.0, 0.0 or both: the ARMAR-4 balance-reward evidence (issue 7), same seed and budget;
# "both" trains the two settings side by side on the one GPU (each its own process and 45 % of its
# memory) and stops them after TB seconds: each evaluation writes a checkpoint and a progress row, so
# a stopped pair still compares at the last step both reached. The ARMAR-4 URDF travels as
# .whl/armar4_slim.tgz (the armar package with only the files armar4_fixed_hands.urdf names) and the dataset as
# .whl/balance_splines (scripts/balance_evidence.py writes it); the run directories come back as
# $OUT/balance_runs.tgz.
if [ -n "${BALANCE:-}" ]; then
  if [ -f .whl/armar4_slim.tgz ] && ! python3 -c "import armar" 2>/dev/null; then
    mkdir -p /tmp/site && tar xzf .whl/armar4_slim.tgz -C /tmp/site || exit 1
    export PYTHONPATH=/tmp/site:${PYTHONPATH:-}
  fi
  BROOT=${BROOT:-/tmp/balance_splines}; BOUT=${BOUT:-/tmp/balance_runs}
  [ -d .whl/balance_splines ] && [ ! -d "$BROOT" ] && cp -r .whl/balance_splines "$BROOT"
  if [ "${SMALL:-0}" = 1 ]; then NB=16; BB=8; TSB=1600; NE=3; else NB=${NB:-2048}; BB=${BB:-512}; TSB=${TSB:-12000000}; NE=${NE:-9}; fi
  SCALES=$BALANCE; [ "$BALANCE" = both ] && SCALES="1.0 0.0"
  echo "=== balance $SCALES ($(date +%T), limit ${TB:-540}s each)"
  for s in $SCALES; do
    XLA_PYTHON_CLIENT_MEM_FRACTION=0.45 timeout "${TB:-540}" python3 scripts/balance_evidence.py --root "$BROOT" \
      --out "$BOUT" --num-envs $NB --batch-size $BB --num-timesteps $TSB --scales "$s" \
      --num-minibatches 8 --num-evals $NE --compilation-cache "/tmp/jax_cache_$s" > "$OUT/balance_$s.log" 2>&1 &
  done
  wait
  echo "=== stopped $(date +%T)"
  for s in $SCALES; do grep -v "import warp\|import mujoco_warp" "$OUT/balance_$s.log" | tail -n 12; done
  tar czf "$OUT/balance_runs.tgz" -C "$BOUT" .
  exit
fi
# BALL="flags": one ball-on-plate training run (issue 23) with the CPU recipe's reward flags given in
# BALL (e.g. BALL="--beta 4 --jerk-reward 3 --ball-reward 4") on 2048 environments (NBALL), TSBALL
# steps, stopped after TBALL seconds; every evaluation writes a checkpoint, so a stopped run still
# comes back with its last one: $OUT/ball_run.tgz (evaluate it here with evaluate.py --checkpoint).
if [ -n "${BALL:-}" ]; then
  NBALL=${NBALL:-2048}; TSBALL=${TSBALL:-60000000}
  [ "${SMALL:-0}" = 1 ] && { NBALL=64; TSBALL=200000; }
  echo "=== ball $BALL ($(date +%T), limit ${TBALL:-520}s)"
  # shellcheck disable=SC2086
  timeout "${TBALL:-520}" python3 train.py --task ball_on_plate --preset paper $BALL --num-envs "$NBALL" \
    --batch-size $((NBALL / 4)) --num-minibatches 16 --num-timesteps "$TSBALL" --num-evals "${NEBALL:-13}" \
    --out /tmp/ball_run --compilation-cache /tmp/jax_cache_ball 2>&1 | grep -v "import warp\|import mujoco_warp" \
    | tee "$OUT/ball.log"
  echo "=== stopped $(date +%T)"
  tar czf "$OUT/ball_run.tgz" --exclude tensorboard -C /tmp ball_run
  exit
fi
# smoke: fail fast if the stack does not import
python3 -c "import mjx_pathtrack, jax; from mjx_pathtrack import training; print(jax.__version__, jax.devices())" 2>&1 \
  | grep -v warp || exit 2
nvidia-smi --query-gpu=name,memory.total,clocks.sm --format=csv 2>/dev/null | tee "$OUT/gpu.txt"
run limits_dt0.1 60 python3 benchmarks/bench_limits.py --batch $BL --dt 0.1
run limits_dt0.05 60 python3 benchmarks/bench_limits.py --batch $BL --dt 0.05
run limits_big 60 python3 benchmarks/bench_limits.py --batch $((BL * 16)) --dt 0.1
run env_kinematic 60 python3 benchmarks/bench_env.py --batch $B
run env_mjx 90 python3 benchmarks/bench_env.py --batch $B --executor mjx
run train_bench 120 python3 benchmarks/bench_train.py --num-envs $B --num-timesteps $TS
# learning-budget exploration for issue 5 (papers' reward; then alpha 1): eval lines every 10 M steps
run train_alpha2 $T1 python3 train.py --out /tmp/run_a2 --num-envs $E --batch-size $BS --num-minibatches 8 \
  --num-timesteps $((TS * 20)) --num-evals 7 --eval-episodes 256
[ "$T2" -gt 0 ] && run train_alpha1 $T2 python3 train.py --out /tmp/run_a1 --alpha 1.0 --num-envs $E --batch-size $BS \
  --num-minibatches 8 --num-timesteps $((TS * 20)) --num-evals 7 --eval-episodes 256
echo "=== done $(date +%T)"
