#!/usr/bin/env bash
# Build examples/cpp/filter_one_state.cpp against a prebuilt ONNX Runtime and run it.
#
#   examples/cpp/build_and_run.sh                 # export the Air3D switch filter, then check its decisions
#   examples/cpp/build_and_run.sh FILTER.onnx --state X1,X2,... --u U1,... [--t T]   # filter one state
#
# ONNX Runtime's C/C++ headers and a Linux x86-64 libonnxruntime.so come from one npm package,
# com.github.asus4.onnxruntime (a Unity packaging of ONNX Runtime 1.29.0; `npm pack` fetches it
# from the npm registry, about 150 MB, checked against the SHA-256 below). The headers are those of
# the official Android archive inside it (Plugins/Android/onnxruntime.aar, headers/). Neither
# Python's onnxruntime wheel nor Debian 12 ships the headers.
#
# Everything lands in the build folder ($REACH_CPP_BUILD, default examples/cpp/build, git-ignored);
# a second run reuses the library and headers found there. Needs npm, g++ (C++17), tar, and unzip
# or python3 to open the archive; without a FILTER.onnx, also the `reach` command (the project's
# virtual environment) to export one.
set -euo pipefail

here="$(cd "$(dirname "$0")" && pwd)"
build="${REACH_CPP_BUILD:-$here/build}"
package=com.github.asus4.onnxruntime
version=0.4.9
sha256=e59788788818fdde1b2e522e766a21ba0f7d8391de55737abf81e32cc801785d
ort="$build/onnxruntime-1.29.0"

if [[ "$(uname -s)-$(uname -m)" != Linux-x86_64 ]]; then
    echo "build_and_run.sh: the package ships its Linux library for x86-64 only, not $(uname -s)-$(uname -m)" >&2
    exit 2
fi
for tool in npm g++ tar sha256sum; do
    command -v "$tool" >/dev/null || { echo "build_and_run.sh: needs $tool" >&2; exit 2; }
done
mkdir -p "$build"

# 1. ONNX Runtime: headers and library, fetched once.
if [[ ! -f "$ort/lib/libonnxruntime.so.1" || ! -f "$ort/include/onnxruntime_cxx_api.h" ]]; then
    fetch="$(mktemp -d "$build/fetch.XXXXXX")"
    trap 'rm -rf "$fetch"' EXIT
    (cd "$fetch" && npm pack "$package@$version" --silent >/dev/null)
    echo "$sha256  $fetch/$package-$version.tgz" | sha256sum -c --quiet -
    tar -xzf "$fetch/$package-$version.tgz" -C "$fetch" \
        package/Plugins/Linux/x64/libonnxruntime.so package/Plugins/Android/onnxruntime.aar
    rm -rf "$ort" && mkdir -p "$ort/include" "$ort/lib"
    aar="$fetch/package/Plugins/Android/onnxruntime.aar"
    if command -v unzip >/dev/null; then
        unzip -q -j "$aar" 'headers/*' -d "$ort/include"
    else  # the headers alone, flat, as unzip -j does
        python3 -c 'import os, sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as archive:
    for name in archive.namelist():
        if name.startswith("headers/") and not name.endswith("/"):
            with open(os.path.join(sys.argv[2], os.path.basename(name)), "wb") as out:
                out.write(archive.read(name))' "$aar" "$ort/include"
    fi
    # the library's soname is libonnxruntime.so.1: the loader looks for that name
    mv "$fetch/package/Plugins/Linux/x64/libonnxruntime.so" "$ort/lib/libonnxruntime.so.1"
    ln -sf libonnxruntime.so.1 "$ort/lib/libonnxruntime.so"
    rm -rf "$fetch"
    trap - EXIT
    echo "fetched ONNX Runtime headers and library into $ort"
fi

# 2. Build: one translation unit, linked against libonnxruntime with its folder as the run path.
g++ -std=c++17 -O2 -Wall -Wextra -I"$ort/include" "$here/filter_one_state.cpp" \
    -L"$ort/lib" -lonnxruntime -Wl,-rpath,"$ort/lib" -o "$build/filter_one_state"
echo "built $build/filter_one_state"

# 3a. A given filter: filter the given state and stop.
if [[ $# -gt 0 ]]; then
    exec "$build/filter_one_state" "$@"
fi

# 3b. No filter given: export Air3D's switch filter and check the decisions on known states.
filter="$build/air3d-switch.onnx"
# (its warnings go to a log, shown if the export fails)
if ! reach export pretrained:air3d --out "$filter" --kind switch --dt 0.05 2>"$build/export.log"; then
    cat "$build/export.log" >&2
    exit 1
fi

checks=0
# run NAME WANT_EXIT WANT_LINE ARGS...: run the example, print what it printed, and check its exit
# status and that one line of its output is exactly WANT_LINE
run() {
    local name="$1" want_exit="$2" want_line="$3" out status
    shift 3
    echo "== $name: filter_one_state $*"
    set +e
    out="$("$build/filter_one_state" "$@" 2>&1)"
    status=$?
    set -e
    echo "$out"
    if [[ $status -ne $want_exit ]] || ! grep -qxF -- "$want_line" <<<"$out"; then
        echo "check failed: $name: wanted exit $want_exit and the line '$want_line'" >&2
        exit 1
    fi
    checks=$((checks + 1))
}
# the two aircraft in collision (relative position 0): the filter replaces the nominal input
run collision 0 "flags: intervened=1 infeasible=0 outside_domain=0" "$filter" --state 0,0,0 --u 1 --t 1.1
# far apart, heading away: the nominal input passes
run clear 0 "flags: intervened=0 infeasible=0 outside_domain=0" "$filter" --state 0.9,0,0 --u 1 --t 0.5
# no time-to-go: avoid's default (the horizon, 1.1 s) is taken
run default-time 0 "time_to_go: 1.10000002 (the export's default)" "$filter" --state 0.9,0,0 --u 1
# outside the domain: the backup input, whatever the value says
run outside-domain 0 "flags: intervened=1 infeasible=0 outside_domain=1" "$filter" --state 3,1,0 --u 1 --t 1.1
# refusals before the graph runs
run nan-state 3 "refused: states contain NaN or inf (or overflow float32), e.g. [nan,0,0]" \
    "$filter" --state nan,0,0 --u 1 --t 1.1
run overflow-input 3 "refused: u_nominal contain NaN or inf (or overflow float32), e.g. [1e+300]" \
    "$filter" --state 0,0,0 --u 1e300 --t 1.1
run late-time 3 "refused: time-to-go t = 2 lies outside [0, 1.1], the times this value function covers" \
    "$filter" --state 0,0,0 --u 1 --t 2
run short-state 3 "refused: states must have 3 entries, got 2" "$filter" --state 0,0 --u 1 --t 1.1
echo "build_and_run.sh: $checks checks passed"
