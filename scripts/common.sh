# Shared by the scripts that make committed files again: run from the repository's root, a
# timed step, and the release build of celld they all call.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

step() {
    local name=$1
    shift
    echo "== $name: $*"
    local started=$SECONDS
    "$@"
    echo "== $name: done in $((SECONDS - started)) s"
}

echo "== building celld (release)"
cargo build --release
CELLD=./target/release/celld
