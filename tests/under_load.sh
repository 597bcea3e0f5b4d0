#!/usr/bin/env bash
# The test suite on a busy machine: `python -m pytest` (the README's test command) while
# LOAD_JOBS other jobs (default 2: both cores of a 2-core machine) keep the CPU busy, each
# `yes > /dev/null`. The jobs are killed when the suite ends, fails, or is stopped with
# Ctrl-C or SIGTERM. Prints how long the suite took.
#
#   tests/under_load.sh                  # from the repository root; extra arguments go to pytest
#   LOAD_JOBS=4 PYTHON=.venv/bin/python tests/under_load.sh -x tests/bridge/test_agents.py
#
# See docs/testing.md: the real-time tests judge what their run recorded and skip, naming the
# measured numbers, when the machine could not keep their deadline.
set -u
set -m   # job control: the jobs below get their own process groups, so a Ctrl-C reaches this
         # script only, and its trap passes it on to pytest (and stops the load)
jobs=${LOAD_JOBS:-2}
py=${PYTHON:-python}
pids=()

stop_load() {
    if [ ${#pids[@]} -gt 0 ]; then
        kill "${pids[@]}" 2>/dev/null
        wait "${pids[@]}" 2>/dev/null
        pids=()
    fi
}
trap stop_load EXIT
trap 'stop_load; exit 130' INT
trap 'stop_load; exit 143' TERM HUP

for _ in $(seq "$jobs"); do
    yes > /dev/null &
    pids+=($!)
done
echo "under_load.sh: $jobs busy job(s) (yes > /dev/null: pids ${pids[*]}); running $py -m pytest $*" >&2
start=$(date +%s)
# pytest in the background and waited for: the INT/TERM traps run at once, not after it ends
"$py" -m pytest "$@" &
test_pid=$!
trap 'kill -INT $test_pid 2>/dev/null; wait $test_pid; stop_load; exit 130' INT
trap 'kill -TERM $test_pid 2>/dev/null; wait $test_pid; stop_load; exit 143' TERM HUP
wait $test_pid
rc=$?
stop_load
echo "under_load.sh: the suite took $(( $(date +%s) - start )) s with $jobs busy job(s); pytest exit status $rc" >&2
exit $rc
