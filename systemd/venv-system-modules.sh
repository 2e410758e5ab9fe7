#!/usr/bin/env bash
# Make a few Python modules that only the system's package manager provides importable in a
# venv, and nothing else of the system's Python packages (docs/decisions.md, "Cameras: the
# venv and GStreamer's Python bindings"):
#   gi         GStreamer's Python bindings (Debian: python3-gi) for `gst:` camera pipelines;
#   libcamera  libcamera's bindings (Raspberry Pi OS: python3-libcamera) for `picamera2:`;
#   pykms      (Raspberry Pi OS: python3-kms++), which picamera2 imports.
# Each module is a symlink in VENV/system-modules to the system's dist-packages, and a .pth
# file in the venv's site-packages appends that folder to sys.path: the venv's own packages
# still come first, and no other system package (an older numpy, say) can shadow or leak in.
#
# Usage: venv-system-modules.sh VENV [MODULE...]   (default: gi). A module that is not
# installed, or that was built for another Python version than the venv's (Ubuntu 22.04's
# python3-gi is for 3.10), is reported and skipped: exit code 0 unless VENV is not a venv.
set -euo pipefail

VENV=${1:?usage: $0 VENV [MODULE...]}
shift || true
MODULES=${*:-gi}
DIST=${SYSTEM_DIST_PACKAGES:-/usr/lib/python3/dist-packages}
PYTHON=$VENV/bin/python
[ -x "$PYTHON" ] || {
	echo "venv-system-modules: $VENV is not a venv (no bin/python)" >&2
	exit 1
}
VENV=$(cd "$VENV" && pwd)
LINKS=$VENV/system-modules
SITE=$("$PYTHON" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
TAG=$("$PYTHON" -c 'import sysconfig; print(sysconfig.get_config_var("SOABI"))') # cpython-311-...

say() { printf 'venv-system-modules: %s\n' "$*"; }

mkdir -p "$LINKS"
for m in $MODULES; do
	src=$DIST/$m
	if [ ! -e "$src" ]; then
		say "$m: not in $DIST (not installed; see docs/install.md, Cameras): skipped"
		continue
	fi
	# a package with compiled parts must have them for this interpreter's ABI
	if find -L "$src" -maxdepth 2 -name '*.cpython-*.so' | grep -q . &&
		! find -L "$src" -maxdepth 2 -name "*.$TAG.so" | grep -q .; then
		say "$m: $src is built for another Python than $("$PYTHON" -V 2>&1) ($TAG): skipped;" \
			"install it into the venv from PyPI instead (docs/install.md, Jetson)"
		continue
	fi
	ln -sfn "$src" "$LINKS/$m"
done
echo "$LINKS" >"$SITE/companion-system-modules.pth"
for m in $MODULES; do
	if [ -e "$LINKS/$m" ]; then
		if "$PYTHON" -c "import $m" 2>/dev/null; then
			say "$m: importable in $VENV"
		else
			say "$m: linked but \`import $m\` fails in $VENV:"
			"$PYTHON" -c "import $m" 2>&1 | tail -1 | sed 's/^/  /'
		fi
	fi
done
