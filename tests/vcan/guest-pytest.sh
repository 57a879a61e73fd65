# Body of the guest script that tests/vcan/run boots (it prepends REPO, PYTHON, PYTEST_ARGS).
# Runs in the QEMU guest, chrooted into the host's read-only root: pytest on tests/vcan/, with
# vcan0's kernel counters read before and after. Results go to $VCAN_OUT (a writable 9p share).
set -u
counters() {  # tx_packets rx_packets tx_dropped rx_dropped backlog_drops
    local d=/sys/class/net/vcan0/statistics backlog=0 line
    while read -r line; do  # second column of softnet_stat: frames dropped from the backlog
        set -- $line
        backlog=$((backlog + 16#$2))
    done </proc/net/softnet_stat
    echo "$(<$d/tx_packets) $(<$d/rx_packets) $(<$d/tx_dropped) $(<$d/rx_dropped) $backlog"
}
read -r tx0 rx0 txd0 rxd0 bl0 < <(counters)
cd "$REPO" || exit 2
export PYTHONDONTWRITEBYTECODE=1 MPLCONFIGDIR=/tmp/mpl
"$PYTHON" -m pytest -p no:cacheprovider -q tests/vcan "${PYTEST_ARGS[@]}" 2>&1 |
    tee "$VCAN_OUT/pytest.log"
rc=${PIPESTATUS[0]}
read -r tx1 rx1 txd1 rxd1 bl1 < <(counters)
tx=$((tx1 - tx0)) rx=$((rx1 - rx0)) lost=$((txd1 - txd0 + rxd1 - rxd0 + bl1 - bl0))
{
    echo "pytest: $(grep -aE '^(=+ )?[0-9]+ (passed|failed|skipped|error)|no tests ran' \
        "$VCAN_OUT/pytest.log" | tail -1) (exit $rc)"
    echo "vcan0: $tx frames sent, $rx delivered (kernel counters);" \
        "dropped: tx $((txd1 - txd0)), rx $((rxd1 - rxd0)), backlog $((bl1 - bl0))"
    if ((lost == 0)); then
        echo "vcan0: no frame lost"
    else
        echo "vcan0: FRAMES LOST"
    fi
} >"$VCAN_OUT/summary.txt"
if ((rc == 0 && lost != 0)); then rc=1; fi
exit "$rc"
