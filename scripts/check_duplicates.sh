#!/usr/bin/env bash
# Fails when the change repeats code already in the tree to the letter (the team's `duplicates`
# tool, `duplicates --change`); pairs alike in shape only (argument lists, signatures) are shown
# but pass. Skipped with a note where the tool is not installed.
set -euo pipefail
if ! command -v duplicates >/dev/null; then
  echo "duplicates not installed: repeated-code check skipped"
  exit 0
fi
out=$(duplicates --change "$@")
echo "$out"
# A row a pair: "D1 a.py:10-24 ~ b.py:40-54", with " shape" where no run is the same to the letter.
if grep -E '^D[0-9]+ ' <<<"$out" | grep -vqE ' shape( |$)'; then
  echo "the change repeats code: make one piece serve both places"
  exit 1
fi
