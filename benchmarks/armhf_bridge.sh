#!/usr/bin/env bash
# Target-platform check of the bridge (issue 20): Debian 12 armhf, the BeagleBone Blue's system,
# emulated with qemu-user, with the bridge installed as the robot has it (docs/bridge.md,
# "Deployment on the BeagleBone"): apt's python3-numpy, python3-lz4, python3-zstandard, gcc, then
# pip for this package's base install (zenoh's armv7l wheel, msgspec compiled from source, typer,
# mcap). Then `xneck bridge --driver replay` and `--driver beaglebone` (rcpy faked at the library
# boundary, tests/fake_rcpy) run for a bounded time against a hub on the host.
# Reports: install success and time, import time, resident memory (VmHWM of the emulated process:
# it includes qemu's own memory and translated code, an upper bound of the board's), states the
# host received, ticks and overruns (qemu's timing is not the Cortex-A8's).
#
# Needs root (debootstrap, chroot, binfmt_misc), the package registries, and about 1 GB in /tmp.
# Run: sudo bash benchmarks/armhf_bridge.sh [SECONDS]      (default 20 s per driver)
# The root file system is kept in $XNECK_ARMHF_ROOT (default /tmp/xneck-armhf/root) and reused.
set -euo pipefail
SECONDS_PER_DRIVER="${1:-20}"
REPO="${XNECK_REPO:-$(cd "$(dirname "$0")/.." && pwd)}"
HOST_PY="${XNECK_HOST_PYTHON:-$REPO/.venv/bin/python}"
ROOTFS="${XNECK_ARMHF_ROOT:-/tmp/xneck-armhf/root}"
WORK="$(dirname "$ROOTFS")"
MIRROR="${XNECK_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
LOG="$WORK/armhf_bridge.log"
mkdir -p "$WORK"
: > "$LOG"
say() { echo "armhf: $*" | tee -a "$LOG"; }
fail() { say "FAILED: $*"; exit 1; }
[ "$(id -u)" = 0 ] || fail "run as root (debootstrap, chroot and binfmt_misc need it)"

# 1. Host tools: Debian's debootstrap and qemu-user-static.
if ! command -v debootstrap >/dev/null || [ ! -x /usr/bin/qemu-arm-static ]; then
    say "installing debootstrap, qemu-user-static, binfmt-support (apt)"
    apt-get update -qq >>"$LOG" 2>&1
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
        debootstrap qemu-user-static binfmt-support >>"$LOG" 2>&1 || fail "apt-get install (see $LOG)"
fi

# 2. binfmt_misc: ARM binaries run through qemu-arm (F: the interpreter is opened now, so it works
#    inside the chroot too).
if [ ! -e /proc/sys/fs/binfmt_misc/register ]; then
    mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc || fail "cannot mount binfmt_misc"
fi
if [ ! -e /proc/sys/fs/binfmt_misc/qemu-arm ]; then
    update-binfmts --enable qemu-arm >>"$LOG" 2>&1 || update-binfmts --import qemu-arm >>"$LOG" 2>&1 \
        || fail "cannot register qemu-arm in binfmt_misc"
fi
grep -q enabled /proc/sys/fs/binfmt_misc/qemu-arm || fail "qemu-arm is registered but disabled"

# 3. Debian 12 armhf root file system (minbase + python3), once.
if [ ! -x "$ROOTFS/usr/bin/python3" ]; then
    say "debootstrap bookworm armhf into $ROOTFS (several minutes under qemu)"
    rm -rf "$ROOTFS"
    debootstrap --arch=armhf --variant=minbase --include=python3,ca-certificates bookworm "$ROOTFS" "$MIRROR" \
        >>"$LOG" 2>&1 || fail "debootstrap (see $LOG)"
fi

mounted=()
cleanup() {
    local i
    for ((i = ${#mounted[@]} - 1; i >= 0; i--)); do umount -l "${mounted[i]}" 2>/dev/null || true; done
    [ -n "${HUB_PID:-}" ] && kill "$HUB_PID" 2>/dev/null || true
    [ -n "${BRIDGE_PID:-}" ] && kill "$BRIDGE_PID" 2>/dev/null || true
}
trap cleanup EXIT
for fs in proc sys dev; do
    mountpoint -q "$ROOTFS/$fs" || { mount --rbind "/$fs" "$ROOTFS/$fs"; mounted+=("$ROOTFS/$fs"); }
done
cp -L /etc/resolv.conf "$ROOTFS/etc/resolv.conf"
# pip in the root trusts what pip on the host trusts (e.g. a site's TLS-inspecting proxy CA).
ROOT_ENV=(PATH=/usr/local/bin:/usr/bin:/bin HOME=/root LANG=C.UTF-8)
HOST_CERT="${PIP_CERT:-$("$HOST_PY" -m pip config get global.cert 2>/dev/null || true)}"
if [ -n "$HOST_CERT" ] && [ -f "$HOST_CERT" ]; then
    cp -L "$HOST_CERT" "$ROOTFS/etc/ssl/certs/host-pip-ca.crt"
    ROOT_ENV+=(PIP_CERT=/etc/ssl/certs/host-pip-ca.crt)
fi
for var in http_proxy https_proxy no_proxy HTTP_PROXY HTTPS_PROXY NO_PROXY; do
    [ -n "${!var:-}" ] && ROOT_ENV+=("$var=${!var}")
done
in_root() { chroot "$ROOTFS" /usr/bin/env -i "${ROOT_ENV[@]}" "$@"; }
say "target: $(in_root uname -m), Debian $(cat "$ROOTFS/etc/debian_version"), $(in_root python3 --version)"

# 4. The robot's install: apt packages, then pip for the rest (docs/bridge.md).
APT_PACKAGES="python3-venv python3-pip python3-numpy python3-lz4 python3-zstandard python3-dev gcc libc6-dev procps"
if ! in_root dpkg -s $APT_PACKAGES >/dev/null 2>&1; then
    say "apt-get install $APT_PACKAGES"
    in_root apt-get update -qq >>"$LOG" 2>&1 || fail "apt-get update in the armhf root (see $LOG)"
    in_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $APT_PACKAGES \
        >>"$LOG" 2>&1 || fail "apt-get install in the armhf root (see $LOG)"
fi
say "apt: $(in_root dpkg-query -W -f '${Package} ${Version}, ' python3-numpy python3-lz4 python3-zstandard gcc)"
rm -rf "$ROOTFS/opt/xneck-src" "$ROOTFS/opt/fake_rcpy"
mkdir -p "$ROOTFS/opt/xneck-src"
(cd "$REPO" && tar cf - --exclude=__pycache__ pyproject.toml README.md bridge twin controller server) \
    | tar xf - -C "$ROOTFS/opt/xneck-src"
cp -r "$REPO/tests/fake_rcpy" "$ROOTFS/opt/fake_rcpy"
find "$ROOTFS/opt/fake_rcpy" -name __pycache__ -prune -exec rm -rf {} +
say "pip install (system numpy, lz4, zstandard; msgspec built with gcc) into /opt/xneck"
t0=$(date +%s)
if [ "${XNECK_ARMHF_REUSE_INSTALL:-0}" = 1 ] && [ -x "$ROOTFS/opt/xneck/bin/xneck" ]; then
    in_root /opt/xneck/bin/pip install --disable-pip-version-check --no-deps --force-reinstall /opt/xneck-src >>"$LOG" 2>&1 \
        || fail "pip install in the armhf root (see $LOG)"
    INSTALL="ok (dependencies reused from an earlier run: XNECK_ARMHF_REUSE_INSTALL=1)"
elif in_root sh -c 'rm -rf /opt/xneck && python3 -m venv --system-site-packages /opt/xneck &&
        /opt/xneck/bin/pip install --disable-pip-version-check --no-cache-dir /opt/xneck-src' >>"$LOG" 2>&1; then
    INSTALL="ok in $(($(date +%s) - t0)) s"
else
    fail "pip install in the armhf root after $(($(date +%s) - t0)) s (see $LOG)"
fi
say "install: $INSTALL"
say "versions: $(in_root /opt/xneck/bin/python -c 'from importlib.metadata import version as v; print(", ".join(f"{p} {v(p)}" for p in ("numpy", "msgspec", "eclipse-zenoh", "typer", "mcap")))')"
HEAVY=$(in_root /opt/xneck/bin/python -c 'import importlib.util as u; print(" ".join(m for m in ("numba", "llvmlite", "scipy", "matplotlib", "fastapi", "uvicorn", "viser") if u.find_spec(m)) or "none")')
say "heavy packages installed: $HEAVY"

# 5. Import time of what `xneck bridge` loads (command line, bridge, model as plain Python).
IMPORT=$(in_root /opt/xneck/bin/python -c '
import time
t0 = time.perf_counter()
from twin.model.compiled import prefer_plain_python
prefer_plain_python()
import server.cli, bridge.node, bridge.drivers.replay, bridge.archive, controller.laws
t1 = time.perf_counter()
from twin.model.params import load_params
hold = controller.laws.encoder_hold_forces(load_params())
import numpy as np
hold(np.zeros(4))
t2 = time.perf_counter()
hold(np.array([0.3, -0.2, 0.1, 0.0]))
t3 = time.perf_counter()
print(f"imports {t1 - t0:.2f} s, first hold forces {t2 - t1:.2f} s, next {1e3 * (t3 - t2):.0f} ms")')
say "import time (emulated): $IMPORT"

# Resident memory of an idle interpreter under qemu: the emulator's share of the figures below.
chroot "$ROOTFS" /usr/bin/env -i "${ROOT_ENV[@]}" python3 -c 'import time; time.sleep(4)' &
IDLE_PID=$!  # chroot and env exec: this is the interpreter's pid
sleep 3
IDLE_MB=$(awk '/^VmHWM/ {print int($2 / 1024)}' "/proc/$IDLE_PID/status" 2>/dev/null || echo "?")
wait "$IDLE_PID" || true
say "resident memory of an idle python3 under qemu: $IDLE_MB MB"

# 6. Runs against a hub on the host.
rm -f "$ROOTFS/tmp/replay.mcap"
"$HOST_PY" "$REPO/benchmarks/bridge_tick.py" --write-replay "$ROOTFS/tmp/replay.mcap" >>"$LOG" 2>&1 \
    || fail "writing the replay file (see $LOG)"
PORT=$("$HOST_PY" -c 'from bridge.session import free_tcp_port; print(free_tcp_port())')
HUB="tcp/127.0.0.1:$PORT"

run_driver() {  # $1 driver, $2 extra environment for the bridge, rest: bridge options
    local driver="$1" extra_env="$2"; shift 2
    local count_file="$WORK/states_$driver.json"
    rm -f "$count_file"
    "$HOST_PY" - "$HUB" "$((SECONDS_PER_DRIVER + 60))" "$count_file" <<'PY' &
import json, sys, threading, time
from bridge import bus
from bridge.session import open_session
hub, limit_s, out = sys.argv[1], float(sys.argv[2]), sys.argv[3]
seen, drives, lock = [0], {}, threading.Lock()
first = [None]
def on_state(sample):
    try:
        msg = bus.decode(bus.MotorState, sample.payload.to_bytes())
    except bus.BusDecodeError:
        return
    with lock:
        seen[0] += 1
        first[0] = first[0] or time.monotonic()
        drives[msg.drive] = drives.get(msg.drive, 0) + 1
t0 = time.monotonic()
with open_session(listen=[hub], connect=[]) as session:
    sub = session.declare_subscriber(bus.MOTOR_STATE, on_state)
    stop = threading.Event()
    import signal
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait(limit_s)
    sub.undeclare()
with lock:
    json.dump({"states": seen[0], "drives": drives,
               "first_state_after_s": None if first[0] is None else round(first[0] - t0, 1)}, open(out, "w"))
PY
    HUB_PID=$!
    sleep 2
    local t0 peak=0 ticks_log
    t0=$(date +%s)
    chroot "$ROOTFS" /usr/bin/env -i "${ROOT_ENV[@]}" $extra_env \
        /opt/xneck/bin/xneck bridge --driver "$driver" "$@" --connect "$HUB" --listen tcp/127.0.0.1:0 \
        >"$WORK/bridge_$driver.log" 2>&1 &
    BRIDGE_PID=$!
    while kill -0 "$BRIDGE_PID" 2>/dev/null && [ $(($(date +%s) - t0)) -lt "$((SECONDS_PER_DRIVER + 30))" ]; do
        hwm=$(awk '/^VmHWM/ {print int($2 / 1024)}' "/proc/$BRIDGE_PID/status" 2>/dev/null || echo 0)
        [ "${hwm:-0}" -gt "$peak" ] && peak=$hwm
        if grep -q " up: driver" "$WORK/bridge_$driver.log" && [ -z "${up_at:-}" ]; then up_at=$(($(date +%s) - t0)); fi
        if [ -n "${up_at:-}" ] && [ $(($(date +%s) - t0 - up_at)) -ge "$SECONDS_PER_DRIVER" ]; then break; fi
        sleep 0.5
    done
    kill -TERM "$BRIDGE_PID" 2>/dev/null || true
    wait "$BRIDGE_PID" 2>/dev/null && rc=0 || rc=$?
    BRIDGE_PID=""
    sleep 1
    kill -TERM "$HUB_PID" 2>/dev/null || true
    wait "$HUB_PID" 2>/dev/null || true
    HUB_PID=""
    ticks_log=$(grep -o "stopped after.*" "$WORK/bridge_$driver.log" || echo "no stop line (see $WORK/bridge_$driver.log)")
    say "$driver: up after ${up_at:-never} s, exit code $rc, resident memory peak ${peak} MB (qemu included)"
    say "$driver: $ticks_log"
    say "$driver: host received $(cat "$count_file" 2>/dev/null || echo '{"states": 0}')"
    unset up_at
    grep -q '"states": [1-9]' "$count_file" 2>/dev/null
}

ok=0
run_driver replay "" --replay /tmp/replay.mcap --loop || ok=1
run_driver beaglebone "PYTHONPATH=/opt/fake_rcpy" || ok=1
if [ "$ok" = 0 ]; then say "PASSED: installed, started, states received on the host"; else fail "no states received (see $WORK/bridge_*.log)"; fi
