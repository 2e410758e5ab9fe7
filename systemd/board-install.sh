#!/usr/bin/env bash
# Install or remove the companion service on a board, as root: `sudo make install` and
# `sudo make uninstall` run this (docs/install.md, "Install on a board").
#
# install:   the system user `companion` (its own group, plus the groups of the unit's
#            SupplementaryGroups=: dialout for serial ports, video for cameras), a venv with the
#            runtime dependencies only under $PREFIX/venv (this source tree, or WHEEL=FILE),
#            the unit in $UNITDIR (paths rewritten to $PREFIX / $SYSCONFDIR), the config
#            $SYSCONFDIR/config.toml from config/default.toml (never overwritten), the state
#            directory /var/lib/companion, README and docs under $PREFIX, and a `companion`
#            link in $BINDIR. Run again to upgrade: the venv is reinstalled, config and state
#            are kept.
# uninstall: stops and disables the unit and removes all of that except the config and the
#            state (and the user only if install created it).
#
# Environment: PY (python3; must be >= 3.11), PREFIX (/opt/companion), SYSCONFDIR
# (/etc/companion), UNITDIR (/etc/systemd/system), BINDIR (/usr/local/bin), WHEEL (a built
# wheel to install instead of this tree), PIP_ARGS (extra pip arguments, e.g. --no-index
# --find-links DIR for an offline board).
set -euo pipefail
umask 022 # the venv, unit and docs readable by the service user whatever root's umask is

ACTION=${1:-}
SRC=$(cd "$(dirname "$0")/.." && pwd)
PY=${PY:-python3}
PREFIX=${PREFIX:-/opt/companion}
SYSCONFDIR=${SYSCONFDIR:-/etc/companion}
UNITDIR=${UNITDIR:-/etc/systemd/system}
BINDIR=${BINDIR:-/usr/local/bin}
WHEEL=${WHEEL:-}
EXTRAS=${EXTRAS:-}                        # e.g. pi (picamera2): docs/install.md, Cameras
SYSTEM_PY_MODULES=${SYSTEM_PY_MODULES:-gi} # a Pi camera: "gi libcamera pykms"
PIP_ARGS=${PIP_ARGS:-}
VENV=$PREFIX/venv
CONFIG=$SYSCONFDIR/config.toml
STATEDIR=/var/lib/companion # the unit's StateDirectory=companion: fixed by systemd
SERVICE_USER=companion      # the unit's User= and Group=
UNIT_SRC=$SRC/systemd/companion.service
UNIT=$UNITDIR/companion.service
MANIFEST=$PREFIX/.installed # what install created that uninstall may remove
BUILD_DIR=""                # a clean copy of the source tree to build from, removed on exit

say() { printf 'companion install: %s\n' "$*"; }
die() {
	printf 'companion install: error: %s\n' "$*" >&2
	exit 1
}
systemd_running() { [ -d /run/systemd/system ]; }

preflight() {
	[ "$(id -u)" = 0 ] || die "run as root (sudo make $ACTION)"
	case $PREFIX in
	/home/* | /root/* | /root) die "PREFIX=$PREFIX: the unit's ProtectHome= hides /home and /root from the service" ;;
	/*) ;;
	*) die "PREFIX=$PREFIX: an absolute path, please" ;;
	esac
	[ "$(cd "$PREFIX" 2>/dev/null && pwd -P)" != "$(cd "$SRC" && pwd -P)" ] ||
		die "this source tree is PREFIX ($PREFIX): clone or unpack it elsewhere (e.g. /usr/local/src/companion)"
}

install_all() {
	preflight
	command -v "$PY" >/dev/null || die "no $PY: install Python >= 3.11 (docs/install.md)"
	"$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' ||
		die "$("$PY" -V 2>&1) is too old: companion needs Python >= 3.11. On Ubuntu 22.04 / JetPack 6 install python3.11 and python3.11-venv and run: sudo make install PY=python3.11 (docs/install.md, \"Python 3.11 on Ubuntu 22.04 and Jetson\")"
	"$PY" -c 'import ensurepip, venv' 2>/dev/null ||
		die "$PY has no venv support: apt-get install python3-venv (python3.11-venv for python3.11)"
	local base
	base=$("$PY" -c 'import os, sys; print(os.path.realpath(sys.base_prefix))')
	case $base in
	/home/* | /root/* | /root) die "$PY lives in $base: the service user cannot run it there (and the unit's ProtectHome= hides it); use a system Python, e.g. PY=/usr/bin/python3" ;;
	esac
	[ -f "$UNIT_SRC" ] || die "no $UNIT_SRC: run from the source tree (git clone or the sdist)"
	if [ -n "$WHEEL" ]; then
		[ -f "$WHEEL" ] || die "WHEEL=$WHEEL: no such file"
		WHEEL=$(cd "$(dirname "$WHEEL")" && pwd)/$(basename "$WHEEL")
	fi

	mkdir -p "$PREFIX"
	touch "$MANIFEST"

	# 1. the service user, in the groups the unit asks for
	if ! getent passwd "$SERVICE_USER" >/dev/null; then
		useradd --system --user-group --home-dir "$STATEDIR" --no-create-home \
			--shell /usr/sbin/nologin --comment "companion service" "$SERVICE_USER"
		grep -qx 'user' "$MANIFEST" || echo user >>"$MANIFEST"
		say "created system user $SERVICE_USER"
	fi
	local groups g
	groups=$(sed -n 's/^SupplementaryGroups=//p' "$UNIT_SRC")
	for g in $groups; do
		if getent group "$g" >/dev/null; then
			usermod -a -G "$g" "$SERVICE_USER"
		else
			say "warning: no group $g on this system: the unit's SupplementaryGroups= will fail"
		fi
	done

	# 2. the venv: runtime dependencies only (no simulator, evaluation or development extras)
	if [ -x "$VENV/bin/python" ] && ! "$VENV/bin/python" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
		rm -rf "$VENV"
	fi
	"$PY" -m venv "$VENV"
	local pkg
	if [ -n "$WHEEL" ]; then
		pkg=$WHEEL
	else # build from a clean copy: no build/ or *.egg-info left in the source tree, owned by root
		BUILD_DIR=$(mktemp -d)
		trap 'rm -rf "$BUILD_DIR"' EXIT
		cp -r "$SRC/pyproject.toml" "$SRC/README.md" "$SRC/LICENSE" "$SRC/MANIFEST.in" \
			"$SRC/companion" "$SRC/drivers" "$SRC/sitl" "$BUILD_DIR/"
		find "$BUILD_DIR" -name __pycache__ -prune -exec rm -rf {} +
		pkg=$BUILD_DIR
	fi
	say "installing into $VENV (runtime dependencies only)"
	# the dependencies, then companion itself again: an upgrade with the same version number
	# (a newer checkout) must replace the installed code
	# shellcheck disable=SC2086  # PIP_ARGS is a list of arguments
	"$VENV/bin/python" -m pip install --quiet --disable-pip-version-check $PIP_ARGS \
		"$pkg${EXTRAS:+[$EXTRAS]}"
	# shellcheck disable=SC2086
	"$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --force-reinstall \
		--no-deps $PIP_ARGS "$pkg"
	"$VENV/bin/companion" --version >/dev/null || die "$VENV/bin/companion does not start"
	# cameras: the system's GStreamer bindings (gst:), libcamera's (picamera2:) into the venv
	# shellcheck disable=SC2086  # a list of module names
	bash "$SRC/systemd/venv-system-modules.sh" "$VENV" $SYSTEM_PY_MODULES

	# 3. the unit, pointing at this PREFIX and SYSCONFDIR
	mkdir -p "$UNITDIR"
	sed -e "s#/opt/companion/#$PREFIX/#g" -e "s#/etc/companion/#$SYSCONFDIR/#g" "$UNIT_SRC" \
		>"$UNIT.tmp"
	chmod 0644 "$UNIT.tmp"
	mv "$UNIT.tmp" "$UNIT"

	# 4. the config: readable by the service's group only (it may hold an MQTT password);
	#    an existing one is the operator's and is never overwritten
	install -d -m 0750 -o root -g "$SERVICE_USER" "$SYSCONFDIR"
	if [ -e "$CONFIG" ]; then
		say "kept $CONFIG (config/default.toml has the current defaults and comments)"
		if ! runuser -u "$SERVICE_USER" -- test -r "$CONFIG"; then
			chgrp "$SERVICE_USER" "$CONFIG" && chmod g+r "$CONFIG"
			say "made $CONFIG readable by the group $SERVICE_USER"
		fi
	else
		install -m 0640 -o root -g "$SERVICE_USER" "$SRC/config/default.toml" "$CONFIG"
		say "wrote $CONFIG from config/default.toml: edit it for your board"
	fi

	# 5. the state directory (the unit's StateDirectory=; systemd would create it too)
	install -d -m 0700 -o "$SERVICE_USER" -g "$SERVICE_USER" "$STATEDIR"
	chown -R "$SERVICE_USER:$SERVICE_USER" "$STATEDIR"

	# 6. the README the unit's Documentation= names, the docs, and `companion` on PATH
	install -m 0644 "$SRC/README.md" "$PREFIX/README.md"
	install -d -m 0755 "$PREFIX/docs"
	install -m 0644 "$SRC"/docs/*.md "$PREFIX/docs/"
	if [ ! -e "$BINDIR/companion" ] || [ "$(readlink "$BINDIR/companion")" = "$VENV/bin/companion" ]; then
		mkdir -p "$BINDIR"
		ln -sfn "$VENV/bin/companion" "$BINDIR/companion"
		grep -qx 'bin' "$MANIFEST" || echo bin >>"$MANIFEST"
	else
		say "kept $BINDIR/companion (not ours): run $VENV/bin/companion"
	fi

	# 7. check the config as the service will read it, and tell systemd
	if ! runuser -u "$SERVICE_USER" -- "$VENV/bin/companion" config --config "$CONFIG" >/dev/null; then
		say "warning: $CONFIG does not pass \`companion config\` (above): fix it before starting"
	fi
	if systemd_running; then
		systemctl daemon-reload
		say "installed; start with: systemctl enable --now companion"
	else
		say "installed; systemd is not running here: the unit is in place for the next boot"
	fi
}

uninstall_all() {
	preflight
	if systemd_running && [ -e "$UNIT" ]; then
		systemctl disable --now companion.service || true
	fi
	rm -f "$UNIT"
	systemd_running && systemctl daemon-reload
	if [ "$(readlink "$BINDIR/companion" 2>/dev/null)" = "$VENV/bin/companion" ]; then
		rm -f "$BINDIR/companion"
	fi
	rm -rf "$VENV" "$PREFIX/docs"
	rm -f "$PREFIX/README.md"
	if [ -f "$MANIFEST" ] && grep -qx user "$MANIFEST" && getent passwd "$SERVICE_USER" >/dev/null; then
		userdel "$SERVICE_USER"
		getent group "$SERVICE_USER" >/dev/null && groupdel "$SERVICE_USER"
		say "removed system user $SERVICE_USER"
	fi
	rm -f "$MANIFEST"
	rmdir "$PREFIX" 2>/dev/null || say "kept $PREFIX (not empty)"
	say "removed; kept $SYSCONFDIR and $STATEDIR (delete them by hand to forget the config and state)"
}

case $ACTION in
install) install_all ;;
uninstall) uninstall_all ;;
*) die "usage: $0 install|uninstall" ;;
esac
