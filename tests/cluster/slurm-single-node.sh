#!/usr/bin/env bash
# Proof, run by hand (not part of the test command), that scripts/cluster/slurm-array.sbatch
# survives requeues on a real Slurm: it installs Slurm and MUNGE (Debian, as root), brings up a
# one-node cluster in this machine (no systemd, no cgroups), trains three small synthetic
# subjects as a 3-task job array and interrupts two of them while they train:
#   task 1: `scontrol requeue` (Slurm's SIGTERM to every process of the job, as on preemption),
#   task 0: `scancel --batch --signal=USR1` (what --signal=B:USR1@120 sends before the time
#           limit: the batch shell forwards it, drape exits 75, the task requeues itself),
#   task 2: left alone.
# Every run must end complete, the interrupted ones restarted and resumed, and each model.npz
# byte-identical to an uninterrupted local run of the same command (--deterministic).
#
#   tests/cluster/slurm-single-node.sh                      # uses target/release/drape
#   DRAPE=/path/to/drape STEPS=300 tests/cluster/slurm-single-node.sh
#
# Environment:
#   DRAPE            drape binary (default: target/release/drape; it is not built here)
#   WORK             work directory, wiped and reused on every run (default /tmp/drape-slurm)
#   STEPS            training steps per subject (default 200; pick a count that takes 60-90 s,
#                    so the interrupts land mid-run)
#   FRAMES, SIZE     synthetic sequence length and image size (default 12 frames, 64 px)
#   REQUEUE_AT_STEP  interrupt once log.jsonl shows this step (or a checkpoint; default 25)
#   INTERRUPT_USR1   1 (default) also sends task 0 the time-limit signal; 0 leaves it alone
#   CPUS_PER_TASK    CPUs per array task (default 1: two tasks run at once on two CPUs)
#   KILL_WAIT        slurm.conf KillWait, seconds from SIGTERM to SIGKILL (default 30)
#   TIMEOUT          seconds to wait for the whole array (default 1800)
# Exit status 0 when every subject is complete, each interrupted task was requeued and
# resumed, and every model matches; 1 otherwise (with the Slurm logs printed).
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
WORK="${WORK:-/tmp/drape-slurm}"
DRAPE="${DRAPE:-$repo/target/release/drape}"
STEPS="${STEPS:-200}"
FRAMES="${FRAMES:-12}"
SIZE="${SIZE:-64}"
REQUEUE_AT_STEP="${REQUEUE_AT_STEP:-25}"
INTERRUPT_USR1="${INTERRUPT_USR1:-1}"
CPUS_PER_TASK="${CPUS_PER_TASK:-1}"
KILL_WAIT="${KILL_WAIT:-30}"
TIMEOUT="${TIMEOUT:-1800}"
subjects=(alice bob carol)

log() { printf '%s slurm-test: %s\n' "$(date +%T)" "$*"; }
fail() {
    printf '%s slurm-test: FAIL: %s\n' "$(date +%T)" "$*" >&2
    exit 1
}

[ "$(id -u)" -eq 0 ] || fail "run as root (it installs packages and starts the Slurm daemons)"
command -v apt-get >/dev/null || fail "needs Debian (apt-get)"
case "$DRAPE" in /*) ;; *) DRAPE="$PWD/$DRAPE" ;; esac
[ -x "$DRAPE" ] || fail "no drape binary at $DRAPE: build it (cargo build --release -p drape) or set DRAPE"

# 1. Slurm and MUNGE.
missing=()
for pkg in slurm-wlm munge; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    log "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

# Stops the daemon whose pid file this is, if that pid is still the named program.
stop_daemon() { # stop_daemon PIDFILE NAME
    local pid
    pid="$(cat "$1" 2>/dev/null || true)"
    [ -n "$pid" ] && [ "$(cat "/proc/$pid/comm" 2>/dev/null || true)" = "$2" ] || return 0
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do
        kill -0 "$pid" 2>/dev/null || return 0
        sleep 0.2
    done
    echo "slurm-test: $2 (pid $pid) did not stop" >&2
}

# 2. A fresh work directory (only one this script made, marked by .drape-slurm-work).
if [ -e "$WORK" ]; then
    [ -e "$WORK/.drape-slurm-work" ] || fail "$WORK exists and was not made by this script; set WORK"
    # A previous run's daemons may still hold files there.
    stop_daemon "$WORK/run/slurmd.pid" slurmd
    stop_daemon "$WORK/run/slurmctld.pid" slurmctld
    stop_daemon "$WORK/run/munged.pid" munged
    rm -rf "$WORK"
fi
mkdir -p "$WORK"/{etc,munge,run,spool/ctld,spool/d,log,data,runs,local,jobs}
touch "$WORK/.drape-slurm-work"
chmod 700 "$WORK/munge"

host="$(hostname -s)"
cpus="$(nproc)"
mem_mb=$(($(free -m | awk '/^Mem:/ {print $2}') - 1024))
((mem_mb > 512)) || mem_mb=512
export SLURM_CONF="$WORK/etc/slurm.conf"
munge_socket="$WORK/munge/munge.socket.2"

# Cancel the array if it is still there, then stop exactly the daemons this script started.
jobid=""
# shellcheck disable=SC2317 # run by trap
cleanup() {
    if [ -n "$jobid" ] && [ -n "$(squeue -h -j "$jobid" 2>/dev/null)" ]; then
        log "cancelling job $jobid"
        scancel "$jobid" 2>/dev/null || true
        for _ in $(seq $((KILL_WAIT + 15))); do
            [ -z "$(squeue -h -j "$jobid" 2>/dev/null)" ] && break
            sleep 1
        done
    fi
    stop_daemon "$WORK/run/slurmd.pid" slurmd
    stop_daemon "$WORK/run/slurmctld.pid" slurmctld
    stop_daemon "$WORK/run/munged.pid" munged
    log "daemons stopped"
}
trap cleanup EXIT

# 3. MUNGE with a private key and socket, so a system munged (if any) is left alone.
dd if=/dev/urandom of="$WORK/munge/munge.key" bs=1024 count=1 status=none
chmod 600 "$WORK/munge/munge.key"
munged --force --key-file="$WORK/munge/munge.key" --socket="$munge_socket" \
    --pid-file="$WORK/run/munged.pid" --log-file="$WORK/log/munged.log" \
    --seed-file="$WORK/munge/munged.seed"
munge --socket="$munge_socket" -n | unmunge --socket="$munge_socket" >/dev/null \
    || fail "munged does not answer (log: $WORK/log/munged.log)"

# 4. A one-node cluster: no cgroups here, so processes are tracked through /proc.
cat >"$SLURM_CONF" <<EOF
# Written by tests/cluster/slurm-single-node.sh: a one-node test cluster.
ClusterName=drape-test
SlurmctldHost=$host(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$munge_socket
StateSaveLocation=$WORK/spool/ctld
SlurmdSpoolDir=$WORK/spool/d
SlurmctldPidFile=$WORK/run/slurmctld.pid
SlurmdPidFile=$WORK/run/slurmd.pid
SlurmctldLogFile=$WORK/log/slurmctld.log
SlurmdLogFile=$WORK/log/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SwitchType=switch/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
JobRequeue=1
KillWait=$KILL_WAIT
ReturnToService=2
MinJobAge=3600
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/filetxt
JobCompLoc=$WORK/log/jobcomp.log
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
log "slurm.conf: node $host, $cpus CPUs, ${mem_mb} MB, KillWait $KILL_WAIT s ($SLURM_CONF)"
slurmctld
slurmd
deadline=$((SECONDS + 60))
until sinfo -h -n "$host" -o '%T' 2>/dev/null | grep -qx idle; do
    if ((SECONDS > deadline)); then
        sinfo -N -l || true
        tail -n 30 "$WORK/log/slurmctld.log" "$WORK/log/slurmd.log" >&2 || true
        fail "the node did not come up idle in 60 s (logs above)"
    fi
    sleep 1
done
log "node $host is idle: $(sinfo -h -o '%P %a %D %T')"

# 5. Three short synthetic subjects.
: >"$WORK/subjects.txt"
echo "# NAME SEQ_DIR (written by tests/cluster/slurm-single-node.sh)" >>"$WORK/subjects.txt"
for i in "${!subjects[@]}"; do
    name="${subjects[$i]}"
    log "synthesising $name ($FRAMES frames, $SIZE px, seed $((i + 1)))"
    "$DRAPE" synth --out "$WORK/data/$name" --frames "$FRAMES" --size "$SIZE" --seed "$((i + 1))" \
        >"$WORK/data/$name.log" 2>&1 || { cat "$WORK/data/$name.log" >&2; fail "drape synth failed for $name"; }
    echo "$name $WORK/data/$name" >>"$WORK/subjects.txt"
done

# 6. The array.
train_args="--deterministic --steps $STEPS"
jobid="$(cd "$WORK/jobs" && SUBJECTS="$WORK/subjects.txt" RUN_ROOT="$WORK/runs" DRAPE="$DRAPE" \
    DRAPE_TRAIN_ARGS="$train_args" sbatch --parsable --array=0-2 --cpus-per-task="$CPUS_PER_TASK" \
    --output="$WORK/jobs/drape-train-%A_%a.out" "$repo/scripts/cluster/slurm-array.sbatch")"
jobid="${jobid%%;*}"
log "submitted array job $jobid (DRAPE_TRAIN_ARGS=\"$train_args\")"
out_of() { echo "$WORK/jobs/drape-train-${jobid}_$1.out"; }
job_field() { # job_field INDEX FIELD: from scontrol show job, empty once the job is gone
    { scontrol show job -o "${jobid}_$1" 2>/dev/null || true; } | { grep -o "\b$2=[^ ]*" || true; } | head -1 | cut -d= -f2
}
last_step() { # the highest step in a run's log.jsonl (0 when none)
    { grep -ho '"step": *[0-9]*' "$1/log.jsonl" 2>/dev/null || true; } | grep -o '[0-9]*$' | sort -n | tail -1 | grep . || echo 0
}
show_logs() {
    local f
    for f in "$WORK"/jobs/*.out; do
        [ -e "$f" ] && { echo "===== $f"; cat "$f"; }
    done
    echo "===== scontrol show job $jobid"
    scontrol show job "$jobid" 2>&1 || true
    echo "===== slurmctld.log (tail)"
    tail -n 40 "$WORK/log/slurmctld.log" || true
    echo "===== slurmd.log (tail)"
    tail -n 40 "$WORK/log/slurmd.log" || true
    echo "===== jobcomp.log"
    cat "$WORK/log/jobcomp.log" 2>/dev/null || true
}
timeout_fail() {
    show_logs >&2
    fail "$*"
}

# 7. Interrupt tasks 1 (and 0) once they are running and have trained a little.
declare -A interrupt=([1]=requeue)
[ "$INTERRUPT_USR1" = 1 ] && interrupt[0]=usr1
declare -A interrupted_at=() restarts=()
start=$SECONDS
while ((${#interrupted_at[@]} < ${#interrupt[@]})); do
    ((SECONDS - start < TIMEOUT)) || timeout_fail "no interrupt point reached in $TIMEOUT s"
    for i in "${!interrupt[@]}"; do
        [ -z "${interrupted_at[$i]:-}" ] || continue
        run="$WORK/runs/${subjects[$i]}"
        [ -e "$run/complete" ] && fail "task $i finished before it could be interrupted: raise STEPS (now $STEPS)"
        [ "$(job_field "$i" JobState)" = RUNNING ] || continue
        step="$(last_step "$run")"
        [ -e "$run/checkpoint.npz" ] || ((step >= REQUEUE_AT_STEP)) || continue
        if [ "${interrupt[$i]}" = requeue ]; then
            log "task $i (${subjects[$i]}) at step $step: scontrol requeue ${jobid}_$i"
            scontrol requeue "${jobid}_$i"
        else
            log "task $i (${subjects[$i]}) at step $step: scancel --batch --signal=USR1 ${jobid}_$i (as --signal=B:USR1 before the time limit)"
            scancel --batch --signal=USR1 "${jobid}_$i"
        fi
        interrupted_at[$i]=$SECONDS
    done
    sleep 1
done

# 8. Wait for every run to be complete, noting each task's Restarts while Slurm shows it.
while :; do
    done_count=0
    for i in "${!subjects[@]}"; do
        r="$(job_field "$i" Restarts)"
        [ -z "$r" ] || ((r <= ${restarts[$i]:-0})) || restarts[$i]=$r
        [ -e "$WORK/runs/${subjects[$i]}/complete" ] && done_count=$((done_count + 1))
    done
    ((done_count == ${#subjects[@]})) && break
    ((SECONDS - start < TIMEOUT)) || timeout_fail "only $done_count of ${#subjects[@]} runs complete after $TIMEOUT s"
    sleep 2
done
log "all ${#subjects[@]} runs complete in $((SECONDS - start)) s"
# Let Slurm record the last task's end.
for _ in $(seq 30); do
    [ -z "$(squeue -h -j "$jobid" 2>/dev/null)" ] && break
    sleep 1
done

# 9. The same trainings, uninterrupted, outside Slurm.
for name in "${subjects[@]}"; do
    log "local reference run: $name"
    # shellcheck disable=SC2086 # train_args is a word list
    "$DRAPE" train --data "$WORK/data/$name" --out "$WORK/local/$name" $train_args \
        >"$WORK/local/$name.log" 2>&1 || { cat "$WORK/local/$name.log" >&2; fail "local run of $name failed"; }
done

# 10. Verdict: complete, requeued and resumed where interrupted, identical models.
ok=1
# jobcomp/filetxt writes one record per run of a task (a requeued run's record says PENDING).
printf '\n%-8s %-5s %-10s %-5s %-9s %-10s %-8s %s\n' subject task interrupt runs restarts exited-75 resumed identical
for i in "${!subjects[@]}"; do
    name="${subjects[$i]}"
    out="$(out_of "$i")"
    how="${interrupt[$i]:-none}"
    r="${restarts[$i]:-0}"
    # The batch script logs "restart N" at every start (SLURM_RESTART_COUNT).
    logged="$({ grep -o 'restart [0-9]*' "$out" 2>/dev/null || true; } | awk '{print $2}' | sort -n | tail -1)"
    ((${logged:-0} > r)) && r="${logged:-0}"
    runs="$(grep -c "ArrayJobId=$jobid ArrayTaskId=$i " "$WORK/log/jobcomp.log" 2>/dev/null || true)"
    exited75=no resumed=no identical=no
    grep -q 'drape exited 75' "$out" 2>/dev/null && exited75=yes
    grep -q 'decision: resume' "$out" 2>/dev/null && resumed=yes
    if [ -e "$WORK/runs/$name/model.npz" ] && cmp -s "$WORK/runs/$name/model.npz" "$WORK/local/$name/model.npz"; then
        identical=yes
    fi
    printf '%-8s %-5s %-10s %-5s %-9s %-10s %-8s %s\n' "$name" "$i" "$how" "${runs:-0}" "$r" "$exited75" "$resumed" "$identical"
    [ "$identical" = yes ] || ok=0
    if [ "$how" = none ]; then
        [ "$r" = 0 ] && [ "$resumed" = no ] || ok=0
    else
        ((r >= 1)) && [ "$exited75" = yes ] && [ "$resumed" = yes ] || ok=0
    fi
done
echo
if [ "$ok" = 1 ]; then
    log "PASS: every run complete, interrupted tasks requeued and resumed, models byte-identical"
    exit 0
fi
show_logs >&2
fail "see the table and logs above"
