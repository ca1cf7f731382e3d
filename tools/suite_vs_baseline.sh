#!/usr/bin/env bash
# The test suite's wall time against the suite-time baseline's, side by side on this host.
#
# Each round clones both trees afresh (cold kernel caches, as in CI), installs each as its README's test
# command does, then times that command's test part whole (/usr/bin/time: the conftest's compile before
# the first test counts), the baseline first, then the tree. Prints each pair and the median ratio.
#
#   tools/suite_vs_baseline.sh [ROUNDS] [REV]      (default: 1 round of HEAD; baseline bbd34fe)
set -euo pipefail
rounds=${1:-1}
rev=${2:-HEAD}
base=bbd34fe
[[ $rounds =~ ^[1-9][0-9]*$ ]] || { echo "ROUNDS must be a whole number >= 1, got '$rounds'" >&2; exit 2; }
src=$(git -C "$(dirname "$0")/.." rev-parse --show-toplevel)
git -C "$src" rev-parse -q --verify "$rev^{commit}" >/dev/null || { echo "no commit '$rev' in $src" >&2; exit 2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
export CI=true MPLBACKEND=Agg PIP_DISABLE_PIP_VERSION_CHECK=1 NO_MKDOCS_2_WARNING=1

# wall seconds of one tree's README test command; its pytest summary line on stderr
timed_suite() {
    local tree=$1 dir=$2 line
    git clone -q "$src" "$dir" && git -C "$dir" checkout -q "$tree"
    line=$(grep -m1 -E '^python3 -m venv .*pytest' "$dir/README.md") || { echo "$tree: no test command in its README" >&2; return 1; }
    (cd "$dir" && eval "${line% && *}" >"$dir/.install" 2>&1) || { echo "$tree: install failed:" >&2; tail -5 "$dir/.install" >&2; return 1; }
    (cd "$dir" && /usr/bin/time -f %e -o "$dir/.wall" bash -c "${line##*&& }" >"$dir/.out" 2>&1) || true
    echo "  $tree: $(grep -E '(passed|failed|error)' "$dir/.out" | tail -1)" >&2
    cat "$dir/.wall"
}

ratios=()
for r in $(seq "$rounds"); do
    b=$(timed_suite "$base" "$work/base-$r")
    t=$(timed_suite "$rev" "$work/tree-$r")
    ratio=$(python3 -c "print(f'{$t / $b:.3f}')")
    ratios+=("$ratio")
    echo "round $r: baseline $base ${b} s, $rev ${t} s: ${ratio} x"
    rm -rf "$work/base-$r" "$work/tree-$r"
done
echo "median: $(printf '%s\n' "${ratios[@]}" | python3 -c 'import statistics, sys; print(statistics.median(float(x) for x in sys.stdin))') x (target 0.60 x)"
