#!/usr/bin/env bash
# `make check-arm64`: the board's install and a recorded replay on arm64 Debian 12 (Raspberry Pi
# OS bookworm's base), emulated on this x86 machine (issue "Fast enough for a Raspberry Pi",
# docs/install.md, "arm64"). Not in `make test`: under emulation it takes minutes.
#
# 1. the host's tools (qemu-user-static, proot, debootstrap; apt-get installs what is missing);
# 2. an arm64 bookworm root made with debootstrap from the Debian mirror, outside the tree
#    ($ARM64_ROOT), reused when it is there (a second run skips debootstrap). A container has
#    no binfmt_misc, so every arm64 program runs under `proot -q qemu-aarch64-static`, which
#    also catches the children (pip, make, the venv's python);
# 3. the project's wheel, built on the host, installed inside arm64 the two ways a board does:
#    `python3 -m venv && pip install WHEEL` (the dependencies from wheels only:
#    --only-binary=:all:; what came as a wheel and what, if anything, was built is printed from
#    pip's --report) and `make install WHEEL=...` (systemd/board-install.sh: no systemd runs in
#    the root, so the unit is written but not enabled; the script says so itself);
# 4. the first start of the installed `companion` (cold: the first run after the install;
#    warm: the next ones), timed inside the emulation, and the check that the service's and
#    the replay's imports never load numba (only the `sim` extra has it: nothing is compiled
#    at run time on a board);
# 5. `companion eval` on arm64 and on x86 (HOST_PY with this tree) of two recordings, and the
#    poses compared stage by stage (systemd/compare_replays.py: the VO's, then the published
#    ones): a simulated flight recorded on the host (`companion sitl record`, SIM_SECONDS of
#    hills lawnmower), which decides the check, and the committed real clip (CLIP), whose
#    comparison is printed but does not decide it: a camera turned in place by hand, on which
#    round-off alone moves the published ATE by 2x (docs/decisions.md, "Round-off decides
#    the hand-held real sequences"), so arm64's other rounding gives another draw, not an error.
#
# Environment: ARM64_ROOT (/var/tmp/companion-arm64), MIRROR (http://deb.debian.org/debian),
# SUITE (bookworm), HOST_PY (the x86 Python with the project's dependencies: .venv/bin/python),
# CLIP (tests/data/real/tum_fr1_rpy_clip), SIM_SECONDS (10), TOLERANCE_M (1e-6), ATE_REL (0.1:
# poses that differ pass when the two published ATEs agree within 10 %), PIN (host: the arm64 venv gets
# the host venv's versions of every dependency, so that a difference is the architecture's,
# not a release's; none: the newest), SKIP_MAKE_INSTALL (1: only the pip install).
set -euo pipefail
umask 022

SRC=$(cd "$(dirname "$0")/.." && pwd)
ARM64_ROOT=${ARM64_ROOT:-/var/tmp/companion-arm64}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
SUITE=${SUITE:-bookworm}
HOST_PY=${HOST_PY:-$SRC/.venv/bin/python}
CLIP=${CLIP:-$SRC/tests/data/real/tum_fr1_rpy_clip}
SIM_SECONDS=${SIM_SECONDS:-10}
TOLERANCE_M=${TOLERANCE_M:-1e-6}
ATE_REL=${ATE_REL:-0.1}
PIN=${PIN:-host}
SKIP_MAKE_INSTALL=${SKIP_MAKE_INSTALL:-0}
ROOT_PACKAGES="python3 python3-venv python3-pip make ca-certificates"
READY=$ARM64_ROOT/.companion-root-ready # written when the root is complete
CHECK=/var/tmp/companion-check           # inside the root: wheel, clip, venv, replay
HOST_CHECK=$ARM64_ROOT$CHECK
T0=$(date +%s)

say() { printf 'check-arm64: %s\n' "$*"; }
die() {
	printf 'check-arm64: error: %s\n' "$*" >&2
	exit 1
}

# the host's CA bundle, given to pip inside the root: a machine that reaches PyPI through a
# TLS-inspecting proxy trusts that proxy's CA in its own bundle only
HOST_CA=${SSL_CERT_FILE:-/etc/ssl/certs/ca-certificates.crt}
ROOT_CA=/usr/local/share/companion-check/host-ca.pem

# qemu for proot, behind a seccomp filter that answers ENOSYS to statx and faccessat2: proot
# 5.1 (Debian 12's) does not translate the paths of these two newer calls, so a guest's
# `[ -x FILE ]` (glibc's faccessat2) and `ls` (statx) would look at the host's FILE; with
# ENOSYS, qemu and glibc fall back to fstatat, which proot translates. The wrapper execs the
# static qemu copied into the root (proot maps the wrapper's own exec into the guest).
QEMU_IN_ROOT=/usr/local/libexec/qemu-aarch64-static
QEMU_WRAPPER=$ARM64_ROOT/usr/local/libexec/qemu-enosys
qemu_wrapper() {
	mkdir -p "$ARM64_ROOT/usr/local/libexec"
	cmp -s "$(command -v qemu-aarch64-static)" "$ARM64_ROOT$QEMU_IN_ROOT" ||
		cp "$(command -v qemu-aarch64-static)" "$ARM64_ROOT$QEMU_IN_ROOT"
	[ -x "$QEMU_WRAPPER" ] && return
	gcc -O2 -Wall -DQEMU="\"$QEMU_IN_ROOT\"" -x c -o "$QEMU_WRAPPER" - <<'EOF_C'
#include <errno.h>
#include <linux/audit.h>
#include <linux/filter.h>
#include <linux/seccomp.h>
#include <stddef.h>
#include <stdio.h>
#include <sys/prctl.h>
#include <unistd.h>

int main(int argc, char **argv) {
	(void)argc;
	struct sock_filter f[] = {
		BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(struct seccomp_data, arch)),
		BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, AUDIT_ARCH_X86_64, 1, 0),
		BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW),
		BPF_STMT(BPF_LD | BPF_W | BPF_ABS, offsetof(struct seccomp_data, nr)),
		BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, 332 /* statx */, 1, 0),
		BPF_JUMP(BPF_JMP | BPF_JEQ | BPF_K, 439 /* faccessat2 */, 0, 1),
		BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ERRNO | ENOSYS),
		BPF_STMT(BPF_RET | BPF_K, SECCOMP_RET_ALLOW),
	};
	struct sock_fprog prog = {sizeof f / sizeof f[0], f};
	if (prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) || prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER, &prog)) {
		perror("qemu-enosys: seccomp");
		return 127;
	}
	argv[0] = QEMU;
	execv(QEMU, argv);
	perror("qemu-enosys: " QEMU);
	return 127;
}
EOF_C
}

# run a command inside the arm64 root (as its root; a clean environment). Only the device
# nodes a build needs are bound, never the host's /dev: proot runs a guest's mount, umount
# and mknod as the real root on the paths it binds, and debootstrap's second stage unmounts
# /dev/pts and makes /dev/ptmx anew, which took the host's pseudo-terminals away
arm() {
	proot -0 -q "$QEMU_WRAPPER" -r "$ARM64_ROOT" -b /dev/null -b /dev/zero -b /dev/random \
		-b /dev/urandom -b /dev/shm -b /proc -b /sys \
		-b /etc/resolv.conf -w / /usr/bin/env -i HOME=/root LANG=C.UTF-8 \
		PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
		PIP_CERT=$ROOT_CA SSL_CERT_FILE=$ROOT_CA PIP_DISABLE_PIP_VERSION_CHECK=1 "$@"
}

host_tools() {
	local missing="" tool pkg
	for tool in qemu-aarch64-static:qemu-user-static proot:proot debootstrap:debootstrap gcc:gcc; do
		pkg=${tool#*:}
		command -v "${tool%%:*}" >/dev/null || [ -x "/usr/sbin/${tool%%:*}" ] || missing="$missing $pkg"
	done
	if [ -n "$missing" ]; then
		[ "$(id -u)" = 0 ] || die "needs$missing: run as root, or apt-get install$missing"
		say "installing$missing (apt-get)"
		DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing >/dev/null 2>&1 || {
			apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $missing
		}
	fi
	export PATH=$PATH:/usr/sbin:/sbin
	[ -d /proc/sys/fs/binfmt_misc ] && [ -n "$(ls /proc/sys/fs/binfmt_misc 2>/dev/null)" ] &&
		say "binfmt_misc is there; proot is used anyway (it works without it)"
	return 0
}

make_root() {
	if [ ! -f "$READY" ] && [ -x "$ARM64_ROOT/usr/bin/dpkg" ] && [ ! -e "$ARM64_ROOT/debootstrap" ]; then
		# the second stage removes /debootstrap when it succeeds: a complete root, not marked
		echo "Debian $(cat "$ARM64_ROOT/etc/debian_version") arm64, made $(date -u +%F)" >"$READY"
	fi
	if [ -f "$READY" ]; then
		say "reusing the arm64 root $ARM64_ROOT ($(cat "$READY"))"
	else
		[ "$(id -u)" = 0 ] || die "debootstrap needs root"
		if [ ! -x "$ARM64_ROOT/debootstrap/debootstrap" ]; then
			say "debootstrap $SUITE arm64 into $ARM64_ROOT from $MIRROR (first stage)"
			debootstrap --arch=arm64 --foreign --variant=minbase \
				--include="${ROOT_PACKAGES// /,}" "$SUITE" "$ARM64_ROOT" "$MIRROR"
		fi
		# debootstrap in a container links proc to the host's /proc: a folder for proot's bind
		if [ -L "$ARM64_ROOT/proc" ]; then rm "$ARM64_ROOT/proc" && mkdir "$ARM64_ROOT/proc"; fi
		qemu_wrapper
		say "second stage under qemu (slow: every package's scripts run emulated)"
		arm /usr/bin/env DEBOOTSTRAP_DIR=/debootstrap /bin/sh /debootstrap/debootstrap --second-stage
		say "the arm64 root took $(($(date +%s) - T0)) s"
		echo "Debian $(cat "$ARM64_ROOT/etc/debian_version") arm64, made $(date -u +%F)" >"$READY"
	fi
	qemu_wrapper
	mkdir -p "$ARM64_ROOT$(dirname "$ROOT_CA")"
	if [ -f "$HOST_CA" ]; then
		cp "$HOST_CA" "$ARM64_ROOT$ROOT_CA"
	else
		cp "$ARM64_ROOT/etc/ssl/certs/ca-certificates.crt" "$ARM64_ROOT$ROOT_CA"
	fi
	local missing="" p
	for p in $ROOT_PACKAGES; do
		arm dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'ok installed' || missing="$missing $p"
	done
	if [ -n "$missing" ]; then
		say "installing$missing in the arm64 root (apt-get, emulated)"
		arm apt-get -o APT::Sandbox::User=root update -qq
		arm env DEBIAN_FRONTEND=noninteractive apt-get -o APT::Sandbox::User=root install -y -qq $missing
	fi
	say "arm64 root: $(arm uname -m), Debian $(cat "$ARM64_ROOT/etc/debian_version"), $(arm python3 -V)"
}

build_wheel() {
	[ -x "$HOST_PY" ] || die "HOST_PY=$HOST_PY: no such Python (make venv, or HOST_PY=...)"
	rm -rf "$HOST_CHECK"
	mkdir -p "$HOST_CHECK/dist" "$HOST_CHECK/src"
	# a clean copy (no build/ or egg-info in this tree), as board-install.sh does
	cp -a "$SRC/pyproject.toml" "$SRC/README.md" "$SRC/LICENSE" "$SRC/MANIFEST.in" "$SRC/Makefile" \
		"$SRC/companion" "$SRC/drivers" "$SRC/sitl" "$SRC/systemd" "$SRC/config" "$SRC/docs" \
		"$HOST_CHECK/src/"
	find "$HOST_CHECK/src" -name __pycache__ -prune -exec rm -rf {} +
	"$HOST_PY" -m pip wheel -q --no-deps --wheel-dir "$HOST_CHECK/dist" \
		"$HOST_CHECK/src" >/dev/null
	rm -rf "$HOST_CHECK/src/build" "$HOST_CHECK/src"/*.egg-info
	WHEEL=$(cd "$HOST_CHECK/dist" && ls companion-*.whl)
	say "built $WHEEL on the host (pure Python: py3-none-any)"
	: >"$HOST_CHECK/constraints.txt"
	if [ "$PIN" = host ]; then
		"$HOST_PY" -m pip freeze --exclude-editable 2>/dev/null | grep -v -e ' @ ' -e '^companion=' \
			>"$HOST_CHECK/constraints.txt" || true
		say "pinned to the host venv's versions ($(wc -l <"$HOST_CHECK/constraints.txt") in constraints.txt)"
	fi
	cp -a "$CLIP" "$HOST_CHECK/clip"
	say "companion sitl record: a ${SIM_SECONDS} s hills lawnmower, seed 1, on the host"
	(cd "$SRC" && PYTHONPATH=$SRC "$HOST_PY" -m companion.cli sitl record --terrain hills \
		--trajectory lawnmower --seconds "$SIM_SECONDS" --seed 1 --no-progress \
		--out "$HOST_CHECK/sim" >/dev/null)
}

# pip's --report (JSON) as one line per installed distribution: name version wheel|sdist
pip_report() {
	"$HOST_PY" - "$1" <<'EOF'
import json, sys
for item in json.load(open(sys.argv[1]))["install"]:
    meta, url = item["metadata"], item["download_info"]["url"]
    kind = "wheel" if url.endswith(".whl") else "SOURCE (built here)"
    print(f"  {meta['name']:<24} {meta['version']:<12} {kind}: {url.rsplit('/', 1)[-1]}")
EOF
}

pip_install() {
	local t0 binary="--only-binary=:all:"
	say "pip install $WHEEL in a fresh venv inside arm64 (runtime dependencies only)"
	arm python3 -m venv "$CHECK/venv"
	t0=$(date +%s)
	if ! arm "$CHECK/venv/bin/python" -m pip install -q --disable-pip-version-check $binary \
		-c "$CHECK/constraints.txt" --report "$CHECK/pip-report.json" "$CHECK/dist/$WHEEL"; then
		say "not every dependency has an arm64 wheel of the pinned version: again, building what must be"
		binary="--prefer-binary"
		arm "$CHECK/venv/bin/python" -m pip install -q --disable-pip-version-check $binary \
			-c "$CHECK/constraints.txt" --report "$CHECK/pip-report.json" "$CHECK/dist/$WHEEL"
	fi
	say "pip install took $(($(date +%s) - t0)) s (emulated); what it installed ($binary):"
	pip_report "$HOST_CHECK/pip-report.json"
	PIP_BINARY=$binary
}

make_install() {
	if [ "$SKIP_MAKE_INSTALL" = 1 ]; then
		say "make install skipped (SKIP_MAKE_INSTALL=1)"
		COMPANION=$CHECK/venv/bin/companion
		return
	fi
	local t0
	if [ -e "$ARM64_ROOT/opt/companion/.installed" ]; then
		say "make uninstall first (an earlier run's install; its config and state are kept)"
		arm make -C "$CHECK/src" uninstall
	fi
	t0=$(date +%s)
	say "make install WHEEL=$WHEEL inside arm64 (systemd/board-install.sh as root)"
	arm make -C "$CHECK/src" install PY=/usr/bin/python3 WHEEL="$CHECK/dist/$WHEEL" \
		PIP_ARGS="$PIP_BINARY -c $CHECK/constraints.txt"
	say "make install took $(($(date +%s) - t0)) s (emulated); what it left:"
	local f
	for f in /opt/companion/venv/bin/companion /usr/local/bin/companion \
		/etc/systemd/system/companion.service /etc/companion/config.toml /var/lib/companion; do
		if [ -e "$ARM64_ROOT$f" ] || [ -L "$ARM64_ROOT$f" ]; then
			say "  $(arm stat -c '%n %A %U:%G' "$f")$(arm readlink "$f" | sed 's/^/ -> /')"
		else
			say "  $f MISSING"
		fi
	done
	arm getent passwd companion >/dev/null && say "  user: $(arm id companion)"
	COMPANION=/opt/companion/venv/bin/companion
}

first_start() {
	local i config=/etc/companion/config.toml
	[ -f "$ARM64_ROOT$config" ] || config=$CHECK/src/config/default.toml
	# timed inside the emulation; the venv of `pip install` has never run companion (make
	# install's venv has: board-install.sh runs --version and config); pip compiled the
	# bytecode at install, as it does on a board
	say "first start (seconds inside the emulation, not a Pi's):"
	for i in "first" "second" "third"; do
		arm /bin/bash -c "TIMEFORMAT='%R'; { time $CHECK/venv/bin/companion --version >/dev/null 2>&1; } 2>&1" |
			sed "s/^/  companion --version, $i run after pip install: /; s/\$/ s/"
	done
	for i in "first" "second"; do
		arm /bin/bash -c "TIMEFORMAT='%R'; { time $CHECK/venv/bin/companion config --config $config >/dev/null 2>&1; } 2>&1" |
			sed "s#^#  companion config --config $config, $i run: #; s/\$/ s/"
	done
	arm /bin/bash -c "TIMEFORMAT='%R'; { time $COMPANION --version >/dev/null 2>&1; } 2>&1" |
		sed "s#^#  $COMPANION --version (after make install): #; s/\$/ s/"
	local venv_py
	venv_py=$(dirname "$COMPANION")/python
	# nothing the service or the replay imports compiles at run time: numba is not installed,
	# and not even tried (the `sim` extra only)
	arm "$venv_py" -c '
import importlib.util, sys
import companion.cli, companion.service.app, companion.offline, companion.reporting
assert importlib.util.find_spec("numba") is None, "numba is installed in the runtime venv"
loaded = sorted({"numba", "llvmlite", "skimage", "matplotlib", "evo"} & set(sys.modules))
assert not loaded, loaded
print("check-arm64: numba: not installed, not imported by the service or eval (nothing to cache)")
'
}

# the libraries both replays run on, once
versions() {
	local show='import cv2, numpy, scipy, platform, sys
print(f"check-arm64: {sys.argv[1]:5} {platform.machine()}: numpy {numpy.__version__}, scipy {scipy.__version__}, opencv {cv2.__version__}")'
	"$HOST_PY" -c "$show" x86
	arm "$(dirname "$COMPANION")/python" -c "$show" arm64
}

# replay NAME: `companion eval $CHECK/NAME` on arm64 and on x86, the poses compared; the
# compare's code (0 equal, 3 different but equally accurate, 1 not, 2 a file missing)
replay() {
	local t0 name=$1
	say "companion eval $name on arm64 (emulated)"
	t0=$(date +%s)
	arm "$COMPANION" eval "$CHECK/$name" --out "$CHECK/eval-arm64-$name" --no-progress | tail -3
	say "arm64 replay took $(($(date +%s) - t0)) s"
	say "companion eval $name on x86 ($HOST_PY, this tree)"
	t0=$(date +%s)
	(cd "$SRC" && PYTHONPATH=$SRC "$HOST_PY" -m companion.cli eval "$HOST_CHECK/$name" \
		--out "$HOST_CHECK/eval-x86-$name" --no-progress | tail -1)
	say "x86 replay took $(($(date +%s) - t0)) s"
	say "poses of $name, x86 against arm64:"
	local code=0
	"$HOST_PY" "$SRC/systemd/compare_replays.py" "$HOST_CHECK/eval-x86-$name" \
		"$HOST_CHECK/eval-arm64-$name" --tolerance-m "$TOLERANCE_M" --ate-rel "$ATE_REL" || code=$?
	# 0: equal; 3: different but equally accurate (the stages below say where the difference
	# starts); 1: different and not; 2: a file missing or malformed
	[ "$code" = 1 ] || [ "$code" = 3 ] || return $code
	# where the difference starts: the frontend's steps on the first two frames, each stage of
	# arm64 fed with x86's output of the stage before
	say "the poses of $name differ: the frontend's stages on the first two frames, arm64 against x86:"
	cp "$SRC/systemd/compare_replays.py" "$HOST_CHECK/"
	(cd "$SRC" && "$HOST_PY" systemd/compare_replays.py --probe "$HOST_CHECK/$name" \
		"$HOST_CHECK/probe-x86-$name.npz")
	arm "$(dirname "$COMPANION")/python" "$CHECK/compare_replays.py" --probe "$CHECK/$name" \
		"$CHECK/probe-arm64-$name.npz" --reference "$CHECK/probe-x86-$name.npz"
	"$HOST_PY" "$SRC/systemd/compare_replays.py" --probe-diff "$HOST_CHECK/probe-x86-$name.npz" \
		"$HOST_CHECK/probe-arm64-$name.npz"
	return $code
}

host_tools
make_root
build_wheel
pip_install
make_install
first_start
versions
set +e
replay sim
code=$?
replay clip
clip_code=$?
set -e
# the simulated flight decides: equal (0) or equally accurate (3) passes
[ "$code" = 3 ] && code=0
case $clip_code in
0 | 3) say "the real clip: x86 and arm64 agree (equal, or ATEs within $ATE_REL)" ;;
1) say "the real clip: the ATEs differ by more than $ATE_REL (printed, not failed: see the top of this script)" ;;
*) say "the real clip: the comparison could not run (code $clip_code)" && code=$clip_code ;;
esac
say "done in $(($(date +%s) - T0)) s; outputs in $HOST_CHECK"
exit $code
