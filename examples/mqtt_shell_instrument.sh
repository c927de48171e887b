#!/bin/sh
# An instrument made only of Debian's mosquitto_sub and mosquitto_pub (apt-get install mosquitto-clients),
# written from docs/mqtt.md alone: it "measures" a quantum-dot sample by reading back its emission peak.
#
#   examples/mqtt_shell_instrument.sh HOST PORT TOPIC [SECONDS]
#
# Run commands are answered after SECONDS (wall time) with {"id", "outputs": {"peak_nm"}, "sample"}; a second
# command while one runs is refused as busy; a cancel stops the running one and is acknowledged; a ping
# re-announces "online". status is "online" (retained) while it runs and "offline" when it exits or dies.
set -u
H=$1 P=$2 T=$3 SECS=${4:-1}
STATE=$(mktemp -d)
: > "$STATE/job"

pub() { mosquitto_pub -h "$H" -p "$P" -q 1 -t "$T/$1" -m "$2" ${3:-}; }

handle() {
  while IFS= read -r line; do
    id=$(printf '%s\n' "$line" | sed -n 's/^{"id": "\([^"]*\)".*/\1/p')
    case "$line" in
      *'"ping": true'*) pub status online -r ;;
      *'"cancel": true'*)
        if [ "$(cat "$STATE/job")" = "$id" ]; then
          kill "$(cat "$STATE/pid")" 2>/dev/null
          : > "$STATE/job"
          pub result "{\"id\": \"$id\", \"cancelled\": true}"
        fi ;;
      *)
        if [ -s "$STATE/job" ]; then
          pub result "{\"id\": \"$id\", \"refused\": \"busy\", \"infeasible\": false}"
          continue
        fi
        printf '%s' "$id" > "$STATE/job"
        (
          sleep "$SECS"
          sample=$(printf '%s\n' "$line" | sed 's/.*"sample": \(.*\)}$/\1/')
          peak=$(printf '%s\n' "$sample" | sed -n 's/.*"peak_nm": \([-0-9.eE+]*\).*/\1/p')
          if [ -z "$peak" ]; then
            pub result "{\"id\": \"$id\", \"error\": \"no peak_nm in the sample\"}"
          else
            pub result "{\"id\": \"$id\", \"outputs\": {\"peak_nm\": $peak}, \"sample\": $sample}"
          fi
          : > "$STATE/job"
        ) &
        echo $! > "$STATE/pid" ;;
    esac
  done
}

mkfifo "$STATE/in"
mosquitto_sub -h "$H" -p "$P" -q 1 -t "$T/command" \
  --will-topic "$T/status" --will-payload offline --will-retain --will-qos 1 > "$STATE/in" &
SUB=$!
handle < "$STATE/in" &
HANDLER=$!
trap 'kill $SUB $HANDLER 2>/dev/null; pub status offline -r; rm -rf "$STATE"; exit 0' INT TERM
pub health '{"ok": true, "made_of": "mosquitto_sub and mosquitto_pub"}' -r
pub status online -r
echo "ready $T"
wait
