# Sourced by scripts/test: the MQTT tests start their own mosquitto on loopback, and one
# instrument is made only of Debian's mosquitto_sub/mosquitto_pub; this makes sure both
# packages are installed (apt does not start the broker).
if ! { command -v mosquitto >/dev/null 2>&1 || [ -x /usr/sbin/mosquitto ]; } || ! command -v mosquitto_pub >/dev/null 2>&1; then
  echo "labtwin: installing mosquitto and mosquitto-clients (apt-get) for the MQTT tests" >&2
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  PKGS="mosquitto mosquitto-clients"
  if ! { $SUDO apt-get install -y -qq $PKGS >/dev/null 2>&1 || { $SUDO apt-get update -qq >/dev/null 2>&1 && $SUDO apt-get install -y -qq $PKGS >/dev/null 2>&1; }; }; then
    echo "labtwin: could not install mosquitto; install it (apt-get install -y mosquitto mosquitto-clients) and run again" >&2
    exit 1
  fi
fi
