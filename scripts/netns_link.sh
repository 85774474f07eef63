#!/bin/bash
# Two "machines" on this host for the multi-machine experiment: network namespaces maem_cam
# (camera publishers) and maem_fus (association, triangulation, the benchmark's listener),
# joined by one veth pair 10.66.0.1 <-> 10.66.0.2 whose both directions are shaped by tc to
# RATE (default 1gbit; e.g. 100mbit). Traffic never leaves the host. Root required.
#
#   sudo scripts/netns_link.sh up [RATE]     # create (or re-shape) the link
#   sudo scripts/netns_link.sh down          # remove both namespaces
#
# Then, as root, from the repository (ROS discovery runs over the link: SUBNET range,
# UDP only, so nothing takes a shared-memory shortcut between the namespaces):
#   export ROS_DOMAIN_ID=66 ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET \
#          FASTRTPS_DEFAULT_PROFILES_FILE=$PWD/config/fastdds_udp.xml
#   ip netns exec maem_fus .venv/bin/maem-bench --live --publisher-netns maem_cam --wire q4 \
#          --vertex-stride 8
set -euo pipefail
cmd=${1:-up}
rate=${2:-1gbit}
if [ "$cmd" = down ]; then
    ip netns del maem_cam 2>/dev/null || true
    ip netns del maem_fus 2>/dev/null || true
    exit 0
fi
if ! ip netns list | grep -qw maem_cam; then
    ip netns add maem_cam
    ip netns add maem_fus
    ip link add maem_veth_c type veth peer name maem_veth_f
    ip link set maem_veth_c netns maem_cam
    ip link set maem_veth_f netns maem_fus
    ip -n maem_cam addr add 10.66.0.1/24 dev maem_veth_c
    ip -n maem_fus addr add 10.66.0.2/24 dev maem_veth_f
    for ns in maem_cam maem_fus; do
        ip -n $ns link set lo up
    done
    ip -n maem_cam link set maem_veth_c up multicast on
    ip -n maem_fus link set maem_veth_f up multicast on
    # discovery multicast (239.255.0.1) goes out of the veth
    ip -n maem_cam route add 224.0.0.0/4 dev maem_veth_c
    ip -n maem_fus route add 224.0.0.0/4 dev maem_veth_f
fi
# The publishers of all cameras share one address here, where each camera machine would have
# its own: the kernel's IP reassembly drops a datagram whose fragments interleave with more
# than ipfrag_max_dist (64) fragments from the same address, which six publishers sending
# 64 kB datagrams (44 fragments each) at once exceed (seen: 5 of 1,240 datagrams lost, each a
# ~170 ms reliable-retransmission stall and partial sets). 0 switches the check off, as a
# fusion machine receiving several cameras from one machine should (doc/multi-machine.md).
for ns in maem_cam maem_fus; do
    ip netns exec $ns sysctl -qw net.ipv4.ipfrag_max_dist=0
done
# token bucket on both directions: RATE, 1 ms of burst at that rate (min 32 kB), 100 ms queue
for pair in maem_cam:maem_veth_c maem_fus:maem_veth_f; do
    ns=${pair%%:*}; dev=${pair##*:}
    ip netns exec $ns tc qdisc replace dev $dev root tbf rate "$rate" burst 256kb latency 100ms
done
echo "maem_cam 10.66.0.1 <-> maem_fus 10.66.0.2, $rate each way"
