#!/usr/bin/env bash
# Build on the host every wheel the image installs, so the image build needs no network:
#
#   deploy/wheels/deps/      the project's run-time dependencies, all of them (numpy, trimesh,
#                            embreex, OpenImageIO, grpcio, ...), and requirements.txt naming them
#   deploy/wheels/project/   the dcrad wheel itself, rebuilt on every run (seconds)
#
# The dependency wheels are rebuilt only when pyproject.toml, the pinned versions or the
# Python version change (a stamp in deploy/wheels/deps/ records them). When the Python
# used is a virtualenv with dcrad installed (the default: .venv/bin/python), its installed
# versions pin the wheels, so the containers run exactly the numerics the host's tests ran.
# Only the run-time dependencies of the services go in: no test extras, and not matplotlib,
# which only `dcrad compare` uses to draw its charts (with its own dependencies it would
# add about 95 MB to the image; run `dcrad compare` on a host), nor photompy, which imports
# matplotlib and reads the photometric files of `dcrad solve --luminaires`, which the
# services do not take.
#
# The host's Python must be 3.11 on x86_64 like the image's (Debian bookworm); the
# manylinux wheels run on bookworm's glibc 2.36.
#
# Environment: PYTHON (default .venv/bin/python, else python3); DCRAD_IMAGE_EXCLUDE, the
# dependencies left out of the image, space-separated (default "matplotlib photompy").
set -euo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
cd "$root"
out="$root/deploy/wheels"
if [ -z "${PYTHON:-}" ]; then
    if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
log() { echo "build-wheels: $*" >&2; }

# the image's interpreter is CPython 3.11: wheels for another version would not install there
pyver="$("$PYTHON" -c 'import sys; print("%d.%d" % sys.version_info[:2])')"
if [ "$pyver" != 3.11 ]; then
    log "error: $PYTHON is Python $pyver; the image has Python 3.11 (set PYTHON=python3.11)"
    exit 1
fi
"$PYTHON" -m pip --version >/dev/null

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

# Pins: the versions installed in this environment, as pip constraints (name==version
# lines only; the editable dcrad itself is left out).
"$PYTHON" -m pip freeze --exclude-editable 2>/dev/null | grep -E '^[A-Za-z0-9_.-]+==[^ ]+$' >"$tmp/constraints.txt" || true

# -- the project wheel -------------------------------------------------------------------
# Built from a clean copy of the source (the files git tracks or would track, as they are in
# the work tree), so a stale build/ folder or a stray file cannot end up in the image.
src="$tmp/src"
mkdir -p "$src"
if git -C "$root" rev-parse --is-inside-work-tree >/dev/null 2>&1; then
    git -C "$root" ls-files -z --cached --others --exclude-standard |
        while IFS= read -r -d '' f; do [ -e "$f" ] && printf '%s\0' "$f"; done |
        tar -C "$root" --null -T - -cf - | tar -C "$src" -xf -
else
    tar -C "$root" --exclude=./.venv --exclude=./build --exclude=./deploy/wheels --exclude=./.git -cf - . | tar -C "$src" -xf -
fi
# Fixed zip timestamps: the same source gives the same wheel, byte for byte, so Docker's
# layer cache keeps the image's dcrad layer when nothing changed.
export SOURCE_DATE_EPOCH="${SOURCE_DATE_EPOCH:-$(git -C "$root" log -1 --format=%ct 2>/dev/null || echo 315532800)}"
# without build isolation when pyproject's build requirements (setuptools>=68, wheel) are
# at hand (no download), else isolated
isolation=(--no-build-isolation)
"$PYTHON" -c 'import sys, setuptools, wheel; sys.exit(int(setuptools.__version__.split(".")[0]) < 68)' \
    2>/dev/null || isolation=()
if ! "$PYTHON" -m pip wheel --no-deps "${isolation[@]}" --wheel-dir "$tmp/project" "$src" >"$tmp/wheel.log" 2>&1; then
    cat "$tmp/wheel.log" >&2
    log "error: building the dcrad wheel failed (log above)"
    exit 1
fi
rm -rf "$out/project"
mkdir -p "$out"
mv "$tmp/project" "$out/project"
log "built $(cd "$out/project" && ls -- *.whl)"

# -- the dependency wheels ---------------------------------------------------------------
# The dependencies of the wheel just built (its METADATA), without extras.
"$PYTHON" - "$out"/project/*.whl "${DCRAD_IMAGE_EXCLUDE-matplotlib photompy}" >"$tmp/requires.txt" <<'EOF'
import re, sys, zipfile
from email.parser import Parser
with zipfile.ZipFile(sys.argv[1]) as z:
    meta = next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))
    msg = Parser().parsestr(z.read(meta).decode())
norm = lambda name: re.sub(r"[-_.]+", "-", name).lower()
exclude = {norm(n) for n in sys.argv[2].split()}
for req in msg.get_all("Requires-Dist") or []:
    name = re.match(r"[A-Za-z0-9._-]+", req).group(0)
    if "extra ==" not in req and norm(name) not in exclude:   # test extras stay out
        print(req)
EOF
# what was left out, for the Dockerfile's `pip check` (which would miss them)
# (one name a line and no empty line: an empty pattern would hide every complaint)
read -r -a excluded <<<"${DCRAD_IMAGE_EXCLUDE-matplotlib photompy}"
: >"$tmp/excluded.txt"
for name in ${excluded[@]+"${excluded[@]}"}; do echo "$name" >>"$tmp/excluded.txt"; done

key="$( { "$PYTHON" -c 'import sys, platform; print(sys.version, platform.machine())'
          cat "$tmp/requires.txt" "$tmp/excluded.txt" "$tmp/constraints.txt" "$0"; } | sha256sum | cut -d' ' -f1)"
if [ -f "$out/deps/.stamp" ] && [ "$(cat "$out/deps/.stamp")" = "$key" ] && [ -s "$out/deps/requirements.txt" ]; then
    log "dependency wheels are up to date in deploy/wheels/deps ($(wc -l <"$out/deps/requirements.txt") packages)"
    exit 0
fi

log "building the dependency wheels (pip wheel; downloads from the package index or pip's cache)"
"$PYTHON" -m pip wheel --quiet --prefer-binary --constraint "$tmp/constraints.txt" \
    --requirement "$tmp/requires.txt" --wheel-dir "$tmp/deps"
# requirements.txt: name==version of every wheel, the closure the image installs
"$PYTHON" - "$tmp/deps" >"$tmp/deps/requirements.txt" <<'EOF'
import pathlib, sys
for whl in sorted(pathlib.Path(sys.argv[1]).glob("*.whl")):
    name, version = whl.name.split("-")[:2]
    print(f"{name}=={version}")
EOF
cp "$tmp/excluded.txt" "$tmp/deps/excluded.txt"
echo "$key" >"$tmp/deps/.stamp"
rm -rf "$out/deps"
mv "$tmp/deps" "$out/deps"
log "built $(wc -l <"$out/deps/requirements.txt") dependency wheels in deploy/wheels/deps ($(du -sh "$out/deps" | cut -f1))"
