#!/usr/bin/env bash
# The GPU checks and benches of issue 14, in one call on a machine with CUDA (a lent GPU machine; CI has none).
#
# Usage: bash scripts/gpu_checks.sh OUT_DIR [STEPS]
#   STEPS: a comma-separated subset of info,tests,sim,adjust_cuda,adjust_cpu (default: all, in that order)
#
# Each step writes its log (and the benches their JSON) to OUT_DIR and goes on when a step fails; the last lines
# printed are a summary: each step's exit code and seconds. Bodies come from the body cache
# ($TORCHGARMENT_CACHE), so the chart sizes 8-20 must be in it when anny is not installed.
set -u
out=${1:?usage: gpu_checks.sh OUT_DIR [STEPS]}
steps=${2:-info,tests,sim,adjust_cuda,adjust_cpu}
mkdir -p "$out"
py=${PYTHON:-python3}
export PYTHONUNBUFFERED=1
summary=()

run_step() {  # name, command...
    local name=$1
    shift
    case ",$steps," in *",$name,"*) ;; *) return ;; esac
    local t0=$SECONDS
    echo "=== $name: $*"
    "$@" >"$out/$name.log" 2>&1
    local rc=$?
    tail -n 25 "$out/$name.log"
    summary+=("$name rc=$rc $((SECONDS - t0)) s")
}

run_step info bash -c "nvidia-smi; uptime; nproc; $py -c 'import torch; print(torch.__version__, torch.cuda.get_device_name(0))'"
run_step tests "$py" -m pytest -q -s -p no:cacheprovider tests/gpu ${GPU_TESTS_K:+-k "$GPU_TESTS_K"}
run_step sim "$py" scripts/bench_sim.py --device cuda --threads 4 --sizes ${SIM_SIZES:-5000 30000 60000} --rounds 4 \
    --profile "${SIM_PROFILE:-0}" --json "$out/bench_sim_cuda.json"
for dev in cuda cpu; do  # the same adjustment on the GPU and on this machine's CPU cores (the baseline)
    run_step "adjust_$dev" timeout "${ADJUST_TIMEOUT:-900}" "$py" scripts/bench_adjust.py --device $dev \
        --threads "$(nproc)" --vertices "${ADJUST_VERTICES:-30000}" --iterations "${ADJUST_ITERATIONS:-256}" \
        --json "$out/bench_adjust_$dev.json"
done

echo "=== summary"
printf '%s\n' "${summary[@]}" | tee "$out/summary.txt"
