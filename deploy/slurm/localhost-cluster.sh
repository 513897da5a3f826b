#!/usr/bin/env bash
# A one-node Slurm cluster on this machine, for CI and for trying deploy/slurm/submit.sh:
# munge, slurmctld and slurmd as root without systemd (ProctrackType=proctrack/pgid,
# TaskPlugin=task/none, SlurmUser=root), the node at 127.0.0.1 with this machine's cores.
# Needs Debian's slurmctld, slurmd, slurm-client and munge. Idempotent: stops what runs first.
#   sudo deploy/slurm/localhost-cluster.sh [start|stop]
set -euo pipefail
action=${1:-start}
pkill -x slurmd 2>/dev/null || true
pkill -x slurmctld 2>/dev/null || true
[ "$action" = stop ] && { pkill -x munged 2>/dev/null || true; exit 0; }
# munge: a key, its directories, the daemon
mkdir -p /etc/munge /var/lib/munge /var/log/munge /run/munge
[ -s /etc/munge/munge.key ] || dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
chmod 700 /etc/munge /var/lib/munge /var/log/munge; chmod 755 /run/munge; chmod 400 /etc/munge/munge.key
chown -R root:root /etc/munge /var/lib/munge /var/log/munge /run/munge
pgrep -x munged >/dev/null || munged --force
# slurm.conf for one node with every core and most of the memory
cpus=$(nproc); mem=$(( $(awk '/MemTotal/{print $2}' /proc/meminfo) / 1024 * 9 / 10 ))
mkdir -p /etc/slurm /var/spool/slurmctld /var/spool/slurmd /var/log/slurm
cat > /etc/slurm/slurm.conf <<CONF
ClusterName=mortar-ci
SlurmctldHost=localhost(127.0.0.1)
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
ProctrackType=proctrack/pgid
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
# dependent jobs (the merge) start within seconds, not at the next minute's pass
SchedulerParameters=sched_interval=2,sched_min_interval=100000
SchedulerType=sched/builtin
MpiDefault=none
ReturnToService=2
StateSaveLocation=/var/spool/slurmctld
SlurmdSpoolDir=/var/spool/slurmd
SlurmctldLogFile=/var/log/slurm/slurmctld.log
SlurmdLogFile=/var/log/slurm/slurmd.log
SlurmctldPidFile=/run/slurmctld.pid
SlurmdPidFile=/run/slurmd.pid
JobCompType=jobcomp/none
AccountingStorageType=accounting_storage/none
NodeName=localhost NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem State=UNKNOWN
PartitionName=ci Nodes=localhost Default=YES MaxTime=INFINITE State=UP
CONF
slurmctld
slurmd
# the node up
for _ in $(seq 1 30); do
  if sinfo -h -o %T 2>/dev/null | grep -qE '^(idle|mixed|allocated)'; then sinfo; exit 0; fi
  scontrol update nodename=localhost state=resume >/dev/null 2>&1 || true
  sleep 1
done
echo "the Slurm node did not come up:" >&2; sinfo >&2 || true; tail -20 /var/log/slurm/slurmctld.log /var/log/slurm/slurmd.log >&2 || true
exit 1
