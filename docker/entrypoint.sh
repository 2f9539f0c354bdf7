#!/bin/sh
# Entrypoint of docker/Dockerfile: run `autotuner ARGS` as the unprivileged user autotuner. Given
# CAP_SYS_NICE (compose: cap_add: [SYS_NICE]), it is kept as an ambient capability across the switch —
# the only one — so the daemon's samplers can raise their scheduling priority (docs/daemon.md, "A plant").
# Docker gives a container started as a non-root user no capabilities at all, cap_add or not: hence the
# image starts as root and drops to autotuner here. Started as another user (docker run --user), it runs as is.
set -eu
if [ "$(id -u)" != 0 ]; then
    exec autotuner "$@"
fi
export HOME=/home/autotuner USER=autotuner LOGNAME=autotuner
bounding=$(sed -n 's/^CapBnd:[[:space:]]*//p' /proc/self/status)
if [ $(( (0x$bounding >> 23) & 1 )) = 1 ]; then    # 23: CAP_SYS_NICE
    exec setpriv --reuid=autotuner --regid=autotuner --init-groups \
        --inh-caps=-all,+sys_nice --ambient-caps=+sys_nice --bounding-set=-all,+sys_nice autotuner "$@"
fi
exec setpriv --reuid=autotuner --regid=autotuner --init-groups --inh-caps=-all --bounding-set=-all autotuner "$@"
