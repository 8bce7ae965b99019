#!/bin/sh
# Beetle-One with its rover and its ground station in two network namespaces, joined by a
# veth pair that drops a fifth of the packets at random each way (nftables) and goes down for
# 10 s every 30 s; operator commands go through the ground station. Needs root, iproute2 and
# nftables (`apt-get install -y nftables iproute2`), and a release build
# (`cargo build --release --workspace`). Usage: scripts/netns-radio.sh [COMMANDS]
set -eu
cd "$(dirname "$0")/.."
DNM=${DNM:-$PWD/target/release/dnm}
export DNM_MODULE_HOST=${DNM_MODULE_HOST:-$PWD/target/release/dnm-module-host}
N=${1:-30}
dir=$(mktemp -d /tmp/dnm-netns-XXXXXX)
echo "logs in $dir"
cleanup() {
    for p in $(jobs -p); do kill "$p" 2>/dev/null || true; done
    ip netns pids rover 2>/dev/null | xargs -r kill 2>/dev/null || true
    ip netns pids ground 2>/dev/null | xargs -r kill 2>/dev/null || true
    sleep 2
    ip netns del rover 2>/dev/null || true
    ip netns del ground 2>/dev/null || true
}
trap cleanup EXIT INT TERM
ip netns add rover
ip netns add ground
ip link add vr type veth peer name vg
ip link set vr netns rover
ip link set vg netns ground
ip -n rover addr add 10.77.0.1/24 dev vr
ip -n ground addr add 10.77.0.2/24 dev vg
for n in rover ground; do ip -n $n link set lo up; done
ip -n rover link set vr up
ip -n ground link set vg up
for n in rover ground; do
    ip netns exec $n nft add table inet radio
    ip netns exec $n nft add chain inet radio in '{ type filter hook input priority 0; }'
    ip netns exec $n nft add rule inet radio in iifname != lo meta random '<' 858993459 drop
done
R="ip netns exec rover"
G="ip netns exec ground"
$R "$DNM" --zenoh-config configs/zenoh/rover-router.json5 --listen tcp/10.77.0.1:7447 \
    --listen tcp/127.0.0.1:7447 router >"$dir/rover-router.log" 2>&1 &
$G "$DNM" --zenoh-config configs/zenoh/ground-router.json5 --listen tcp/127.0.0.1:7448 \
    --connect tcp/10.77.0.1:7447 router >"$dir/ground-router.log" 2>&1 &
sleep 2
$R "$DNM" --zenoh-config configs/zenoh/rover-dnm.json5 up configs/beetle.toml --dnm rover \
    --dnm drive --dnm vision --no-record --state-dir "$dir/rover-state" >"$dir/rover.log" 2>&1 &
$G "$DNM" --zenoh-config configs/zenoh/ground-dnm.json5 up configs/beetle.toml --dnm ground \
    --no-record --state-dir "$dir/ground-state" >"$dir/ground.log" 2>&1 &
$G "$DNM" --zenoh-config configs/zenoh/ground-station.json5 ground serve --system beetle \
    --db "$dir/station.redb" >"$dir/station.log" 2>&1 &
# Outages: the radio goes down for 10 s every 30 s.
(while true; do sleep 20; ip -n ground link set vg down; sleep 10; ip -n ground link set vg up; done) &
sleep 8
i=0
while [ $i -lt "$N" ]; do
    i=$((i + 1))
    case $((i % 5)) in
        0) $G "$DNM" ground replace camera --param fov_deg=$((50 + i % 20)) >/dev/null ;;
        1 | 3) $G "$DNM" ground switch auto >/dev/null ;;
        *) $G "$DNM" ground switch teleop >/dev/null ;;
    esac
    sleep 1
done
echo "$N commands queued; waiting for every fate"
t=0
count() { # commands in state $1
    $G "$DNM" ground status --json | python3 -c "import json,sys; print(sum(c['state']=='$1' for c in json.load(sys.stdin)['commands']))"
}
while [ "$(($(count queued) + $(count sent) + $(count acknowledged) + $(count scheduled)))" -gt 0 ]; do
    sleep 2
    t=$((t + 2))
    [ $t -lt 600 ] || { echo "commands still pending after 10 min"; exit 1; }
done
$G "$DNM" ground status | head -8
applied=$(count applied)
echo "applied: $applied of $N"
sleep 3
$R "$DNM" --zenoh-config configs/zenoh/rover-dnm.json5 status --system beetle | grep '^DNM'
late=$(grep -c "arrived after its instant" "$dir/rover.log" || true)
echo "decisions that arrived after their instant: $late"
[ "$applied" -eq "$N" ]
