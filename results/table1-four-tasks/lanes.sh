#!/usr/bin/env bash
# Runs results/table1-four-tasks/queue.txt on two lanes (or $1): each lane takes the next command that no lane has
# taken in this launch. Finished runs return at once (resume=auto); a stopped run resumes from its checkpoint.
# From the repository root, in its virtual environment:  bash results/table1-four-tasks/lanes.sh [lanes]
# Each command's output goes to runs/every-task/.queue/log.<line>; SIGTERM to a run checkpoints it and ends
# its lane.
set -u
queue="$(dirname "$0")/queue.txt"
lanes="${1:-2}"
state=runs/every-task/.queue
mkdir -p "$state"
# a launch beside a running one (more lanes) keeps its claims; a fresh launch clears the last launch's
if ! { [[ -f "$state/lanes.pid" ]] && kill -0 "$(cat "$state/lanes.pid")" 2>/dev/null; }; then
    rm -rf "$state"/taken.*
    echo $$ > "$state/lanes.pid"
fi

lane() {
    while :; do
        local picked="" n=0 cmd="" line
        while IFS= read -r line; do
            n=$((n + 1))
            [[ -z "$line" || "$line" == \#* ]] && continue
            mkdir "$state/taken.$n" 2>/dev/null || continue
            picked=$n cmd=$line
            break
        done < "$queue"
        [[ -z "$picked" ]] && { echo "lane $1: queue done"; return; }
        echo "$(date -u +%FT%TZ) lane $1: line $picked: $cmd"
        eval "$cmd" >> "$state/log.$picked" 2>&1
        local rc=$?
        echo "$(date -u +%FT%TZ) lane $1: line $picked ended with status $rc"
        if [[ $rc -ge 128 ]]; then return; fi  # stopped by a signal (checkpointed): the lane stops too
    done
}

for i in $(seq 1 "$lanes"); do
    lane "$i" &
    sleep 5
done
wait
