#!/usr/bin/env bash
# DDS sends a completed cloud (tens of MB) as one UDP sample; the kernel drops what a reader's
# receive buffer cannot hold, and RustDDS repairs it slowly. The ROS 2 DDS tuning guide's fix:
# raise net.core.rmem_max. This raises it to 64 MiB when it is lower and this user may (root,
# writable /proc/sys); it never lowers it. Called by setup.sh and test.sh.
want=67108864
f=/proc/sys/net/core/rmem_max
[[ -r $f ]] || exit 0
have=$(cat "$f")
if (( have >= want )); then
  exit 0
fi
if [[ -w $f ]] && echo "$want" > "$f" 2>/dev/null; then
  echo "net.core.rmem_max raised from $have to $want bytes (large ROS 2 messages over DDS)"
else
  echo "warning: net.core.rmem_max is $have bytes; the ROS 2 bridge's 1M-point clouds need more:" \
    "sudo sysctl -w net.core.rmem_max=$want (the ROS 2 loopback test fails without it)" >&2
fi
