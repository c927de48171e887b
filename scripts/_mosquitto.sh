# Sourced by scripts/test: the MQTT tests start their own mosquitto on loopback;
# this makes sure the broker is installed (from Debian; apt does not start it).
if ! command -v mosquitto >/dev/null 2>&1 && [ ! -x /usr/sbin/mosquitto ]; then
  echo "labtwin: installing mosquitto (apt-get) for the MQTT tests" >&2
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  if ! { $SUDO apt-get install -y -qq mosquitto >/dev/null 2>&1 || { $SUDO apt-get update -qq >/dev/null 2>&1 && $SUDO apt-get install -y -qq mosquitto >/dev/null 2>&1; }; }; then
    echo "labtwin: could not install mosquitto; install it (apt-get install -y mosquitto) and run again" >&2
    exit 1
  fi
fi
