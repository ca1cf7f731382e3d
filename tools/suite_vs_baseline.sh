#!/usr/bin/env bash
# The test suite's wall time against the suite-time baseline's, side by side on this host.
#
# Each round clones both trees afresh (cold kernel caches, as in CI), installs each as its README's test
# command does, then times that command's test part whole (/usr/bin/time: the conftest's compile before
# the first test counts), the baseline first, then the tree. Prints each pair and the median ratio.
#
#   tools/suite_vs_baseline.sh [ROUNDS] [REV]      (default: 1 round of HEAD; baseline bbd34fe)
#
# A suite still running after SUITE_TIMEOUT_S (default 1800 s) is ended with its process group and its
# round left out: a test run that hangs at its exit has no wall time to compare.
set -euo pipefail
rounds=${1:-1}
rev=${2:-HEAD}
base=bbd34fe
limit=${SUITE_TIMEOUT_S:-1800}
[[ $rounds =~ ^[1-9][0-9]*$ ]] || { echo "ROUNDS must be a whole number >= 1, got '$rounds'" >&2; exit 2; }
src=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
git -C "$src" rev-parse -q --verify "$rev^{commit}" >/dev/null || { echo "no commit '$rev' in $src" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export CI=true MPLBACKEND=Agg PIP_DISABLE_PIP_VERSION_CHECK=1 NO_MKDOCS_2_WARNING=1

# wall seconds of one tree's README test command ("timeout" if it ran past the limit); its pytest summary
# line on stderr
timed_suite() {
    local tree=$1 dir=$2 line rc=0
    git clone -q "$src" "$dir" && git -C "$dir" checkout -q "$tree"
    line=$(grep -m1 -E '^python3 -m venv .*pytest' "$dir/README.md") || { echo "$tree: no test command in its README" >&2; return 1; }
    (cd "$dir" && eval "${line% && *}" >"$dir/.install" 2>&1) || { echo "$tree: install failed:" >&2; tail -5 "$dir/.install" >&2; return 1; }
    (cd "$dir" && /usr/bin/time -f %e -o "$dir/.wall" timeout -k 30 "$limit" bash -c "${line##*&& }" >"$dir/.out" 2>&1) || rc=$?
    # whatever the suite left running (a helper it never joined, a worker started as it was ended) runs this
    # tree's interpreter: ended with it
    pkill -KILL -f "$dir/" || true
    echo "  $tree: $(grep -E '(passed|failed|error)' "$dir/.out" | tail -1)" >&2
    if [[ $rc == 124 || $rc == 137 ]]; then
        echo "  $tree: still running after ${limit} s: ended" >&2
        echo timeout
    else
        tail -1 "$dir/.wall"
    fi
}

ratios=()
for r in $(seq "$rounds"); do
    b=$(timed_suite "$base" "$work/base-$r")
    t=$(timed_suite "$rev" "$work/tree-$r")
    if [[ $b == timeout || $t == timeout ]]; then
        echo "round $r: left out (a suite ran past ${limit} s)"
        rm -rf "$work/base-$r" "$work/tree-$r"
        continue
    fi
    ratio=$(python3 -c "print(f'{$t / $b:.3f}')")
    ratios+=("$ratio")
    echo "round $r: baseline $base ${b} s, $rev ${t} s: ${ratio} x"
    rm -rf "$work/base-$r" "$work/tree-$r"
done
(( ${#ratios[@]} )) || { echo "no round to compare"; exit 1; }
echo "median: $(printf '%s\n' "${ratios[@]}" | python3 -c 'import statistics, sys; print(statistics.median(float(x) for x in sys.stdin))') x (target 0.60 x)"
