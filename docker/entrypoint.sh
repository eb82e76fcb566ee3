#!/bin/sh
# Runs the container's command; with JOIN_RAY_CLUSTER=host:port it first joins that Ray cluster as a node that
# offers no CPUs to actors, so the service's Ray calls go through a local raylet (settings: ray.address = "auto")
# and the robot actors land on the worker nodes.
set -e
if [ -n "$JOIN_RAY_CLUSTER" ]; then
    .venv/bin/ray start --address="$JOIN_RAY_CLUSTER" --num-cpus=0 --disable-usage-stats
fi
exec "$@"
