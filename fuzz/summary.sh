#!/usr/bin/env bash
# Sums the logs of fuzz/run.sh: per target, the time fuzzed, the executions, the
# slowest input, the peak memory, and the findings left under fuzz/artifacts.
cd "$(dirname "$0")"
printf '| target | hours fuzzed (wall) | CPU hours (where recorded) | executions | slowest input (s) | peak RSS (MB) | findings |\n|---|---|---|---|---|---|---|\n'
for log in logs/*.log; do
  t=$(basename "$log" .log)
  awk -v t="$t" -v found="$(find artifacts/"$t" -type f 2>/dev/null | wc -l)" '
    /^== [0-9]/ { done = 0 }
    /^Done [0-9]+ runs in [0-9]+ second/ { s += $5; done = 1 }
    /^== end: / { if (!done) s += $3 }
    /^== cpu: / { cpu += $3 }
    /number_of_executed_units/ { e += $2 }
    /slowest_unit_time_sec/ { if ($2 > slow) slow = $2 }
    /peak_rss_mb/ { if ($2 > rss) rss = $2 }
    END { printf "| %s | %.2f | %.2f | %d | %d | %d | %d |\n", t, s / 3600, cpu / 3600, e, slow, rss, found }
  ' "$log"
done
