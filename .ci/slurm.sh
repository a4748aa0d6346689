#!/usr/bin/env bash
# Single-node Slurm cluster with accounting, for tests and CI only.
#
# Run as root on Debian 12 without systemd. It installs slurm-wlm, munge, slurmdbd and mariadb-server
# (skipped when already installed), then starts munged -> mariadbd -> slurmdbd -> slurmctld -> slurmd
# by hand, so that sbatch, srun, squeue, sacct and submitit work without any environment variables.
#
#   bash .ci/slurm.sh          start (exits at once when the cluster is already up)
#   bash .ci/slurm.sh status   show the daemons and the node
#   bash .ci/slurm.sh stop     stop the daemons this script started
#   bash .ci/slurm.sh clean    stop, then delete the state folder (next start is from scratch)
#
# All state, pid and log files live in one folder, $DGRL_SLURM_DIR (default /var/tmp/dgrl-slurm).
# The config goes to the default place, /etc/slurm/slurm.conf and /etc/slurm/slurmdbd.conf, so that
# clients find it. Other knobs: DGRL_SLURM_CLUSTER (default dgrl), DGRL_SLURM_DB_PORT (default: the
# first free port from 3307), DGRL_SLURM_TIMEOUT (seconds to wait for each daemon, default 60).
#
# Accounting (slurmdbd + MariaDB) is not optional here: submitit learns a job's fate from sacct, and
# without it a job that dies without writing a result (killed, os._exit, node failure) looks like it
# is still pending, so the caller would wait forever instead of getting an error.
set -euo pipefail

D="${DGRL_SLURM_DIR:-/var/tmp/dgrl-slurm}"
CLUSTER="${DGRL_SLURM_CLUSTER:-dgrl}"
TIMEOUT="${DGRL_SLURM_TIMEOUT:-60}"
HOST="$(hostname -s)"
CONF=/etc/slurm/slurm.conf
DBDCONF=/etc/slurm/slurmdbd.conf
MUNGE_DIR="$D/munge"
MUNGE_SOCK="$MUNGE_DIR/munge.socket"
MUNGE_KEY=/etc/munge/munge.key
DB_DIR="$D/mariadb"
DB_SOCK="$D/mariadb.sock"
PACKAGES=(slurm-wlm munge slurmdbd mariadb-server)

log() { printf '[slurm.sh %3ds] %s\n' "$SECONDS" "$*"; }

# die MESSAGE [LOGFILE]: print the message and the log's tail, then exit non-zero.
die() {
    printf '[slurm.sh %3ds] ERROR: %s\n' "$SECONDS" "$1" >&2
    if [[ -n "${2:-}" && -f "$2" ]]; then
        echo "----- last lines of $2 -----" >&2
        tail -n 40 "$2" >&2
        echo "-----" >&2
    fi
    exit 1
}

# alive NAME PIDFILE: true if the pid file names a running process called NAME.
alive() {
    local pid
    [[ -s "$2" ]] || return 1
    pid="$(tr -dc 0-9 2>/dev/null <"$2")" || return 1
    [[ -n "$pid" && -r "/proc/$pid/comm" ]] || return 1
    [[ "$(cat "/proc/$pid/comm" 2>/dev/null)" == "$1" ]]
}

# wait_for WHAT LOGFILE COMMAND...: retry COMMAND until it succeeds or TIMEOUT seconds pass.
# With PIDFILE=... set, also give up early once that pid file names a process that is gone (daemon died).
wait_for() {
    local what="$1" logfile="$2" start=$SECONDS end=$((SECONDS + TIMEOUT))
    shift 2
    until "$@" >/dev/null 2>&1; do
        ((SECONDS < end)) || die "$what did not come up within ${TIMEOUT}s" "$logfile"
        if [[ -n "${PIDFILE:-}" && -s "$PIDFILE" ]] && ((SECONDS - start >= 2)) && ! alive "${what%% *}" "$PIDFILE"; then
            die "$what exited" "$logfile"
        fi
        sleep 0.5
    done
}

node_state() { timeout 10 sinfo -h -n "$HOST" -o %T 2>/dev/null | head -n 1; }

node_ready() { [[ "$(node_state)" =~ ^(idle|mixed|allocated|completing)$ ]]; }

# Cheap test first (our daemons' pid files), so that a stopped cluster costs no client timeouts.
cluster_up() {
    alive munged "$MUNGE_DIR/munged.pid" && alive slurmdbd "$D/slurmdbd.pid" &&
        alive slurmctld "$D/slurmctld.pid" && alive slurmd "$D/slurmd.pid" &&
        timeout 10 sinfo >/dev/null 2>&1 &&
        timeout 10 sacctmgr -n list cluster >/dev/null 2>&1 &&
        node_ready
}

stop_one() { # stop_one NAME PIDFILE
    local pid i
    if ! alive "$1" "$2"; then
        return 0
    fi
    pid="$(tr -dc 0-9 2>/dev/null <"$2")" || return 0
    log "stopping $1 (pid $pid)"
    kill -TERM "$pid" 2>/dev/null || true
    for ((i = 0; i < 40; i++)); do
        alive "$1" "$2" || return 0
        sleep 0.25
    done
    kill -KILL "$pid" 2>/dev/null || true
}

stop_all() {
    stop_one slurmd "$D/slurmd.pid"
    stop_one slurmctld "$D/slurmctld.pid"
    stop_one slurmdbd "$D/slurmdbd.pid"
    stop_one mariadbd "$D/mariadb.pid"
    stop_one munged "$MUNGE_DIR/munged.pid"
}

status() {
    local rc=0 name pidfile
    for name in munged:"$MUNGE_DIR/munged.pid" mariadbd:"$D/mariadb.pid" slurmdbd:"$D/slurmdbd.pid" \
        slurmctld:"$D/slurmctld.pid" slurmd:"$D/slurmd.pid"; do
        pidfile="${name#*:}"
        name="${name%%:*}"
        if alive "$name" "$pidfile"; then
            printf '%-10s running (pid %s)\n' "$name" "$(tr -dc 0-9 <"$pidfile")"
        else
            printf '%-10s not running\n' "$name"
            rc=1
        fi
    done
    ((rc == 0)) || return "$rc"
    echo "node $HOST: $(node_state || true)"
    timeout 10 sacctmgr -n list cluster format=cluster,controlhost,controlport || rc=1
    return "$rc"
}

install_packages() {
    local missing=0 cmd
    for cmd in slurmctld slurmd slurmdbd sacctmgr munged mungekey mariadbd mariadb-install-db; do
        command -v "$cmd" >/dev/null 2>&1 || missing=1
    done
    if ((missing == 0)); then
        log "packages already installed"
        return 0
    fi
    export DEBIAN_FRONTEND=noninteractive
    # Keep the package scripts from starting the distribution's own munge/mariadb services:
    # the daemons are started below, with private sockets, ports and state.
    local own_policy=0
    if [[ ! -e /usr/sbin/policy-rc.d ]]; then
        printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d
        chmod 755 /usr/sbin/policy-rc.d
        own_policy=1
        trap 'rm -f /usr/sbin/policy-rc.d' EXIT
    fi
    local apt_opts=(-y -q --no-install-recommends -o Dpkg::Use-Pty=0)
    log "installing ${PACKAGES[*]}"
    if ! compgen -G '/var/lib/apt/lists/*_Packages*' >/dev/null ||
        ! apt-get install "${apt_opts[@]}" "${PACKAGES[@]}" >"$D/apt.log" 2>&1; then
        log "apt-get update, then install again"
        apt-get update -q >>"$D/apt.log" 2>&1 || die "apt-get update failed" "$D/apt.log"
        apt-get install "${apt_opts[@]}" "${PACKAGES[@]}" >>"$D/apt.log" 2>&1 ||
            die "apt-get install failed" "$D/apt.log"
    fi
    if ((own_policy == 1)); then
        rm -f /usr/sbin/policy-rc.d
        trap - EXIT
    fi
    log "packages installed"
}

free_port() { # first port from $1 that nothing listens on
    local p="$1"
    while (exec 3<>"/dev/tcp/127.0.0.1/$p") 2>/dev/null; do
        p=$((p + 1))
    done
    echo "$p"
}

start_munge() {
    if [[ ! -s "$MUNGE_KEY" ]]; then
        log "creating munge key"
        mkdir -p "$(dirname "$MUNGE_KEY")"
        mungekey --create --keyfile="$MUNGE_KEY"
    fi
    chown munge:munge "$MUNGE_KEY"
    chmod 600 "$MUNGE_KEY"
    mkdir -p "$MUNGE_DIR"
    chown -R munge:munge "$MUNGE_DIR"
    # munged refuses a socket folder that other users cannot traverse ("Socket is inaccessible").
    chmod 755 "$MUNGE_DIR"
    if alive munged "$MUNGE_DIR/munged.pid"; then
        log "munged already running"
        return 0
    fi
    log "starting munged"
    rm -f "$MUNGE_SOCK" "$MUNGE_SOCK.lock" "$MUNGE_DIR/munged.pid"
    runuser -u munge -- munged --socket="$MUNGE_SOCK" --key-file="$MUNGE_KEY" \
        --pid-file="$MUNGE_DIR/munged.pid" --log-file="$MUNGE_DIR/munged.log" \
        --seed-file="$MUNGE_DIR/munged.seed" >"$D/munged.err" 2>&1 ||
        die "munged failed to start" "$D/munged.err"
    munge_ok() { munge -n -S "$MUNGE_SOCK" | unmunge -S "$MUNGE_SOCK"; }
    PIDFILE="$MUNGE_DIR/munged.pid" wait_for munged "$MUNGE_DIR/munged.log" munge_ok
}

sql() { mariadb --no-defaults -S "$DB_SOCK" -u root -e "$1"; }

start_mariadb() {
    local port
    if [[ -s "$D/mariadb.port" ]]; then
        port="$(cat "$D/mariadb.port")"
    else
        port="${DGRL_SLURM_DB_PORT:-$(free_port 3307)}"
        echo "$port" >"$D/mariadb.port"
    fi
    if [[ ! -s "$D/db.pass" ]]; then
        (umask 077 && od -An -tx1 -N12 /dev/urandom | tr -d ' \n' >"$D/db.pass")
    fi
    if alive mariadbd "$D/mariadb.pid"; then
        log "mariadbd already running (port $port)"
        return 0
    fi
    if [[ ! -d "$DB_DIR/mysql" ]]; then
        log "initialising the database folder"
        rm -rf "$DB_DIR"
        mariadb-install-db --no-defaults --datadir="$DB_DIR" --user=root \
            --auth-root-authentication-method=normal --skip-test-db >"$D/mariadb-install.log" 2>&1 ||
            die "mariadb-install-db failed" "$D/mariadb-install.log"
    fi
    log "starting mariadbd on 127.0.0.1:$port"
    rm -f "$D/mariadb.pid"
    # innodb_lock_wait_timeout=900 is what slurmdbd asks for (it warns otherwise).
    setsid nohup mariadbd --no-defaults --datadir="$DB_DIR" --socket="$DB_SOCK" --port="$port" \
        --bind-address=127.0.0.1 --user=root --pid-file="$D/mariadb.pid" --log-error="$D/mariadb.log" \
        --innodb-lock-wait-timeout=900 --skip-log-bin </dev/null >>"$D/mariadb.log" 2>&1 &
    PIDFILE="$D/mariadb.pid" wait_for mariadbd "$D/mariadb.log" mariadb-admin --no-defaults -S "$DB_SOCK" -u root ping
    local pass
    pass="$(cat "$D/db.pass")"
    sql "CREATE DATABASE IF NOT EXISTS slurm_acct_db;
         CREATE USER IF NOT EXISTS 'slurm'@'localhost' IDENTIFIED BY '$pass';
         CREATE USER IF NOT EXISTS 'slurm'@'127.0.0.1' IDENTIFIED BY '$pass';
         GRANT ALL ON slurm_acct_db.* TO 'slurm'@'localhost';
         GRANT ALL ON slurm_acct_db.* TO 'slurm'@'127.0.0.1';
         FLUSH PRIVILEGES;" || die "could not create the slurm database user" "$D/mariadb.log"
}

# install_file PATH MODE: write stdin to PATH only when the content changed.
install_file() {
    local tmp
    tmp="$(mktemp "$1.XXXXXX")"
    cat >"$tmp"
    chmod "$2" "$tmp"
    if cmp -s "$tmp" "$1"; then
        rm -f "$tmp"
    else
        mv -f "$tmp" "$1"
    fi
}

write_config() {
    local mem
    mem="$(slurmd -C 2>/dev/null | sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' | head -n 1)"
    [[ -n "$mem" ]] || mem="$(free -m | awk '/^Mem:/ {print $2}')"
    mkdir -p /etc/slurm "$D/state" "$D/spool"
    install_file "$DBDCONF" 600 <<EOF
# Written by .ci/slurm.sh (test/CI cluster); rewritten on every start.
DbdHost=localhost
DbdAddr=127.0.0.1
DbdPort=6819
SlurmUser=root
AuthType=auth/munge
AuthInfo=socket=$MUNGE_SOCK
StorageType=accounting_storage/mysql
StorageHost=127.0.0.1
StoragePort=$(cat "$D/mariadb.port")
StorageUser=slurm
StoragePass=$(cat "$D/db.pass")
StorageLoc=slurm_acct_db
PidFile=$D/slurmdbd.pid
LogFile=$D/slurmdbd.log
EOF
    install_file "$CONF" 644 <<EOF
# Written by .ci/slurm.sh (test/CI cluster); rewritten on every start.
ClusterName=$CLUSTER
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=root
AuthType=auth/munge
CredType=cred/munge
# Own munge socket. cred_expire=10 (default 120): a requeued job may start again only after its old
# credential expired, so with the default a requeue costs two minutes instead of about fifteen seconds.
AuthInfo=socket=$MUNGE_SOCK,cred_expire=10
StateSaveLocation=$D/state
SlurmdSpoolDir=$D/spool
SlurmctldPidFile=$D/slurmctld.pid
SlurmdPidFile=$D/slurmd.pid
SlurmctldLogFile=$D/slurmctld.log
SlurmdLogFile=$D/slurmd.log
# No cgroups needed (containers, no systemd).
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
# The "can not load PMIx library" errors in the logs are harmless noise.
MpiDefault=none
MailProg=/bin/true
# Schedule every 5 s rather than every 60 s, so that tests do not wait on the scheduler.
SchedulerType=sched/backfill
SchedulerParameters=sched_interval=5,bf_interval=5
# Cores only: with CR_Core_Memory and no DefMemPerCPU each job would take all the memory.
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
JobRequeue=1
AccountingStorageType=accounting_storage/slurmdbd
AccountingStorageHost=127.0.0.1
AccountingStoragePort=6819
# Without this slurmctld talks to slurmdbd through the default munge socket ("Protocol authentication error").
AccountingStoragePass=$MUNGE_SOCK
JobAcctGatherType=jobacct_gather/linux
# The node claims 8 CPUs whatever the machine has (config_overrides), so that tests can run
# several one-CPU jobs at once on a small CI machine.
SlurmdParameters=config_overrides
NodeName=$HOST CPUs=8 RealMemory=$mem NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=debug Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
}

# start_daemon NAME: start the Slurm daemon NAME (pid file and log $D/NAME.pid, $D/NAME.log) unless it runs already.
start_daemon() {
    if alive "$1" "$D/$1.pid"; then
        log "$1 already running"
    else
        log "starting $1"
        rm -f "$D/$1.pid"
        "$1" >>"$D/$1.log" 2>&1 || die "$1 failed to start" "$D/$1.log"
    fi
}

start_slurmdbd() {
    start_daemon slurmdbd
    PIDFILE="$D/slurmdbd.pid" wait_for slurmdbd "$D/slurmdbd.log" sacctmgr -n list cluster
    if [[ -z "$(sacctmgr -n -P list cluster format=cluster where cluster="$CLUSTER")" ]]; then
        log "registering cluster $CLUSTER"
        sacctmgr -i add cluster "$CLUSTER" >/dev/null || die "sacctmgr add cluster failed" "$D/slurmdbd.log"
    fi
}

start_slurm() {
    start_daemon slurmctld
    PIDFILE="$D/slurmctld.pid" wait_for slurmctld "$D/slurmctld.log" timeout 3 scontrol ping
    start_daemon slurmd
    # Right after a (re)start the node reads "unknown" for a few seconds: wait on its state.
    PIDFILE="$D/slurmd.pid" wait_for "slurmd (node $HOST idle)" "$D/slurmd.log" node_ready
    log "node $HOST is $(node_state)"
}

start() {
    [[ "$(id -u)" == 0 ]] || die "run as root"
    if [[ -f "$CONF" ]] && command -v sinfo >/dev/null 2>&1 && cluster_up; then
        log "cluster already up (node $HOST is $(node_state))"
        exit 0
    fi
    mkdir -p "$D"
    chmod 755 "$D"
    install_packages
    start_munge
    start_mariadb
    write_config
    start_slurmdbd
    start_slurm
    log "checking with srun and sacct"
    timeout 60 srun -t 1 -J "slurm-sh-check-$$" true || die "srun -t 1 true failed" "$D/slurmctld.log"
    # slurmctld reports to slurmdbd asynchronously: wait until the job shows up in sacct.
    check_recorded() { [[ -n "$(sacct -n -X --name="slurm-sh-check-$$" 2>/dev/null)" ]]; }
    wait_for "job accounting (sacct)" "$D/slurmdbd.log" check_recorded
    local out
    out="$(sacct -n -X)" || die "sacct failed" "$D/slurmdbd.log"
    head -n 5 <<<"$out"
    log "Slurm cluster $CLUSTER up in ${SECONDS}s (state and logs in $D, config in $CONF)"
}

case "${1:-start}" in
start) start ;;
stop) stop_all ;;
status) status ;;
clean)
    stop_all
    log "removing $D"
    rm -rf "$D"
    ;;
*)
    echo "usage: $0 [start|stop|status|clean]" >&2
    exit 2
    ;;
esac
