#!/usr/bin/env bash
# Install SafeMove as a systemd service on the Spark's onboard PC.
# Run as root from a checkout:  sudo systemd/install.sh
# Stage without root side effects:  systemd/install.sh --prefix /tmp/stage
set -euo pipefail

PROG=$(basename "$0")
SCRIPT_DIR=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)

usage() {
    cat <<EOF
Usage: $PROG [--source DIR] [--prefix DIR] [--python PY]

Install the SafeMove runtime as the systemd service safemove.service:
  - system user 'safemove' (no login shell; groups dialout, video, plugdev)
  - the source tree copied to /opt/safemove and pip-installed into /opt/safemove/.venv
  - /etc/safemove/config.yaml and /etc/safemove/calibration.yaml, only if missing
    (an existing config or calibration is never overwritten)
  - /etc/systemd/system/safemove.service and /etc/udev/rules.d/99-spark-base.rules
  - udev reload + trigger, systemctl daemon-reload, config check, systemctl enable

Options:
  --source DIR   source tree to install (default: the checkout holding this script)
  --prefix DIR   stage all files under DIR instead of /; skip useradd, pip, udevadm and
                 systemctl and print them as "would run: ..." (no root needed)
  --python PY    interpreter for the venv (default: python3; must be >= 3.10)
  -h, --help     show this help

The service is enabled but not started: systemctl start safemove (or restart, on an upgrade).
EOF
}

die() {
    echo "$PROG: error: $*" >&2
    exit 1
}

SOURCE="$(cd "$SCRIPT_DIR/.." && pwd)"
PREFIX=""
PYTHON="python3"

while [ $# -gt 0 ]; do
    case "$1" in
        -h|--help) usage; exit 0 ;;
        --source) [ $# -ge 2 ] || die "--source needs a directory"; SOURCE="$2"; shift 2 ;;
        --source=*) SOURCE="${1#*=}"; shift ;;
        --prefix) [ $# -ge 2 ] || die "--prefix needs a directory"; PREFIX="$2"; shift 2 ;;
        --prefix=*) PREFIX="${1#*=}"; shift ;;
        --python) [ $# -ge 2 ] || die "--python needs an interpreter"; PYTHON="$2"; shift 2 ;;
        --python=*) PYTHON="${1#*=}"; shift ;;
        *) echo "$PROG: error: unknown argument '$1' (see --help)" >&2; exit 2 ;;
    esac
done

[ -d "$SOURCE" ] || die "source directory '$SOURCE' does not exist"
SOURCE="$(cd "$SOURCE" && pwd)"

DRY_RUN=0
if [ -n "$PREFIX" ]; then
    DRY_RUN=1
    mkdir -p "$PREFIX" || die "cannot create prefix directory '$PREFIX'"
    PREFIX="$(cd "$PREFIX" && pwd)"
    [ "$PREFIX" != "/" ] || PREFIX=""
    if [ -z "$PREFIX" ]; then DRY_RUN=0; fi
fi

# Paths as seen on the robot (used in commands and messages) ...
APP=/opt/safemove
VENV=$APP/.venv
ETC=/etc/safemove
UNIT_DIR=/etc/systemd/system
RULES_DIR=/etc/udev/rules.d
SERVICE_USER=safemove
SERVICE_GROUPS=(dialout video plugdev)
# ... and where the files are written (under the prefix when staging).
D_APP=$PREFIX$APP
D_ETC=$PREFIX$ETC
D_UNIT_DIR=$PREFIX$UNIT_DIR
D_RULES_DIR=$PREFIX$RULES_DIR

# Run a command, or only print it when staging under --prefix.
run() {
    if [ "$DRY_RUN" -eq 1 ]; then
        printf 'would run:'
        local arg
        for arg in "$@"; do  # quote only where the shell would need it
            if [[ $arg =~ ^[A-Za-z0-9_./,=:@%+-]+$ ]]; then printf ' %s' "$arg"
            else printf ' %q' "$arg"; fi
        done
        printf '\n'
    else
        "$@"
    fi
}

for f in pyproject.toml systemd/safemove.service systemd/99-spark-base.rules \
         runtime/config/default_config.yaml calibration/spark_default.yaml; do
    [ -f "$SOURCE/$f" ] || die "'$SOURCE/$f' is missing (is --source a SafeMove checkout?)"
done

if [ "$DRY_RUN" -eq 0 ]; then
    [ "$(id -u)" -eq 0 ] || die "must run as root (or stage with --prefix DIR)"
    for tool in useradd usermod groupadd getent systemctl udevadm runuser tar "$PYTHON"; do
        command -v "$tool" >/dev/null 2>&1 || die "required command '$tool' not found"
    done
    "$PYTHON" -c 'import sys; sys.exit(sys.version_info < (3, 10))' \
        || die "$PYTHON is older than Python 3.10"
fi

echo "== SafeMove install: source $SOURCE -> ${PREFIX:-/}"

# --- 1. service user ------------------------------------------------------------------
if [ "$DRY_RUN" -eq 1 ]; then
    run useradd --system --user-group --no-create-home --home-dir /var/lib/safemove \
        --shell /usr/sbin/nologin --groups "$(IFS=,; echo "${SERVICE_GROUPS[*]}")" "$SERVICE_USER"
else
    # systemd refuses to start a unit whose SupplementaryGroups= names a missing group.
    for g in "${SERVICE_GROUPS[@]}"; do
        getent group "$g" >/dev/null || groupadd --system "$g" || die "cannot create group '$g'"
    done
    if getent passwd "$SERVICE_USER" >/dev/null; then
        usermod --append --groups "$(IFS=,; echo "${SERVICE_GROUPS[*]}")" "$SERVICE_USER" \
            || die "cannot add user '$SERVICE_USER' to ${SERVICE_GROUPS[*]}"
    else
        useradd --system --user-group --no-create-home --home-dir /var/lib/safemove \
            --shell /usr/sbin/nologin --groups "$(IFS=,; echo "${SERVICE_GROUPS[*]}")" \
            "$SERVICE_USER" || die "cannot create system user '$SERVICE_USER'"
    fi
fi

# --- 2. source tree -> /opt/safemove --------------------------------------------------------
if [ "$SOURCE" = "$D_APP" ]; then
    echo "source is already $D_APP: not copying"
else
    mkdir -p "$D_APP" || die "cannot create '$D_APP'"
    # Remove the previous tree (keeping the venv) so deleted modules do not linger.
    find "$D_APP" -mindepth 1 -maxdepth 1 ! -name .venv -exec rm -rf {} + \
        || die "cannot clean '$D_APP'"
    excludes=(--exclude=./.venv --exclude=./.git --exclude=__pycache__ --exclude='*.egg-info'
              --exclude=./.pytest_cache --exclude=./.ruff_cache --exclude=./.hypothesis
              --exclude=./build --exclude=./dist)
    # Staging inside the source tree: do not copy the stage into itself.
    case "$D_APP/" in
        "$SOURCE"/*)
            rel=${PREFIX#"$SOURCE"/}
            [ "$rel" = "$PREFIX" ] || excludes+=("--exclude=./${rel%%/*}")
            ;;
    esac
    tar -C "$SOURCE" "${excludes[@]}" -cf - . | tar -C "$D_APP" -xf - \
        || die "copying '$SOURCE' to '$D_APP' failed"
    echo "copied $SOURCE -> $D_APP"
fi

# --- 3. venv + package (runtime dependencies only, no dev/export/train extras) -------------
# pyrealsense2's wheel links against libusb-1.0 and fails to import without it.
if ! dpkg-query -W -f='${Status}' libusb-1.0-0 2>/dev/null | grep -q "install ok installed"; then
    run apt-get install -y libusb-1.0-0 || die "cannot install the system package libusb-1.0-0"
fi
if [ -x "$PREFIX$VENV/bin/python" ]; then
    echo "reusing venv $PREFIX$VENV"
else
    run "$PYTHON" -m venv "$VENV" || die "cannot create venv '$VENV'"
fi
run "$VENV/bin/python" -m pip install --upgrade "$APP" || die "pip install of '$APP' failed"

# --- 4. configuration: install only if missing ---------------------------------------------
mkdir -p "$D_ETC" || die "cannot create '$D_ETC'"
install_if_missing() {  # <source file> <destination>
    if [ -e "$2" ] || [ -L "$2" ]; then
        echo "kept existing $2"
    else
        install -m 0644 "$1" "$2" || die "cannot install '$2'"
        echo "installed $2"
    fi
}
if [ -e "$D_ETC/config.yaml" ] || [ -L "$D_ETC/config.yaml" ]; then
    echo "kept existing $D_ETC/config.yaml"
else
    install_if_missing "$SOURCE/runtime/config/default_config.yaml" "$D_ETC/config.yaml"
    # The default config uses the vendor calibration (calibration_file: ''); a fresh install
    # points it at the per-robot copy next to it, which calibration tools update in place.
    if grep -q "^calibration_file: *''" "$D_ETC/config.yaml"; then
        sed -i "s|^calibration_file: *''.*\$|calibration_file: calibration.yaml  # = $ETC/calibration.yaml (set by install.sh)|" \
            "$D_ETC/config.yaml" || die "cannot set calibration_file in '$D_ETC/config.yaml'"
        echo "set calibration_file: calibration.yaml in $D_ETC/config.yaml"
    else
        echo "$PROG: warning: $D_ETC/config.yaml has no \"calibration_file: ''\" line;" \
            "check that it points at $ETC/calibration.yaml" >&2
    fi
fi
install_if_missing "$SOURCE/calibration/spark_default.yaml" "$D_ETC/calibration.yaml"

# --- 5. unit and udev rule -------------------------------------------------------------------
mkdir -p "$D_UNIT_DIR" "$D_RULES_DIR" || die "cannot create '$D_UNIT_DIR' or '$D_RULES_DIR'"
install -m 0644 "$SOURCE/systemd/safemove.service" "$D_UNIT_DIR/safemove.service" \
    || die "cannot install the unit to '$D_UNIT_DIR'"
install -m 0644 "$SOURCE/systemd/99-spark-base.rules" "$D_RULES_DIR/99-spark-base.rules" \
    || die "cannot install the udev rule to '$D_RULES_DIR'"
echo "installed $D_UNIT_DIR/safemove.service and $D_RULES_DIR/99-spark-base.rules"

# Re-apply the rules to serial and USB devices already plugged in (creates /dev/sparkBase).
run udevadm control --reload || die "udevadm control --reload failed"
run udevadm trigger --subsystem-match=tty --subsystem-match=usb --subsystem-match=video4linux \
    || die "udevadm trigger failed"
run systemctl daemon-reload || die "systemctl daemon-reload failed"

# --- 6. validate the config as the service user, then enable ------------------------------
if ! run runuser -u "$SERVICE_USER" -- "$VENV/bin/safemove" config show --config "$ETC/config.yaml"
then
    die "config check failed for $ETC/config.yaml (see above): safemove.service NOT enabled"
fi
run systemctl enable safemove.service || die "systemctl enable safemove.service failed"

echo "== done. Start with: systemctl start safemove   (on an upgrade: systemctl restart safemove)"
