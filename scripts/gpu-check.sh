#!/usr/bin/env bash
# The one-shot GPU check (issue 41, item 6): the wgpu benches and a deep 512² morph on a
# machine with a GPU and no Rust toolchain, in one call of the session's `device` tool.
#
# Here (builds in release, about 15 min cold on 2 cores):
#   scripts/gpu-check.sh prepare
# packs into .gpu-check/pack.tar.xz (ignored by git): the release `deepmorph` with wgpu, the
# `sweep` and `energy` bench executables, the stand-in VGG19 as float16 safetensors (half
# its 80 MB: the tree that travels is at most 64 MiB; float16 rounding of the weights
# changes no cost), the `faces` pair; and the Vulkan loader packages into .gl/
# (/work/.library/device/README.md). Each part of the device run has its own timeout, so
# the table is written whatever hangs.
# Then, with the device tool:
#   run(command="bash scripts/gpu-check.sh device", carry=[".gpu-check", ".gl"], timeout_s=590)
# which writes $OUT/gpu-check.md (the table) and $OUT/gpu-check.log.
#
# Tested here on lavapipe (Mesa's CPU Vulkan) with a small setting:
#   scripts/gpu-check.sh device --small        # 64², one sweep a level; ./gpu-check-out/
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
pack="$root/.gpu-check"
data="$root/../shared/data"

prepare() {
    cd "$root"
    grep -qxF '/.gpu-check/' .git/info/exclude 2>/dev/null || echo '/.gpu-check/' >>.git/info/exclude
    grep -qxF '/.gl/' .git/info/exclude 2>/dev/null || echo '/.gl/' >>.git/info/exclude
    rm -rf "$pack" && mkdir -p "$pack/bin"
    cargo build --release --features wgpu --bin deepmorph --example vgg19_f16
    cp target/release/deepmorph "$pack/bin/"
    # The bench executables: cargo names them by hash, so ask it which they are.
    cargo bench --features wgpu --no-run --bench sweep --bench energy --message-format=json |
        python3 -c '
import json, sys, shutil
for line in sys.stdin:
    m = json.loads(line)
    if m.get("reason") == "compiler-artifact" and "bench" in m["target"]["kind"] and m.get("executable"):
        shutil.copy(m["executable"], sys.argv[1] + "/" + m["target"]["name"])
' "$pack/bin"
    strip "$pack"/bin/*
    target/release/examples/vgg19_f16 "$data/vgg19/vgg19_hed_stand_in.onnx" "$pack/bin/vgg19_f16.safetensors"
    cp "$data"/images/pairs/faces/a.* "$data"/images/pairs/faces/b.* "$pack/bin/"
    # One archive, one xz stream with a dictionary larger than any file: the three
    # executables share most of their code (Burn, wgpu, CubeCL), which a small dictionary
    # compresses three times over (215 MB → 54 MiB at -6, 43 MiB so); xz also takes the
    # identity convolutions' zeros (conv3_4, conv4_4, conv5_4: a quarter of the weights).
    (cd "$pack" && tar -c bin | xz -T1 --lzma2=preset=9,dict=256MiB >pack.tar.xz && rm -rf bin)
    if ! ls .gl/*.deb >/dev/null 2>&1; then
        mkdir -p .gl /tmp/amd64/partial
        local o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
        # shellcheck disable=SC2086
        apt-get $o update -qq
        # shellcheck disable=SC2086
        (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
    fi
    local tree carried
    tree=$(git ls-files -z | xargs -0 du -cb | tail -1 | cut -f1)
    carried=$(du -cb "$pack" .gl | tail -1 | cut -f1)
    echo "tree $((tree >> 20)) MiB + carried $((carried >> 20)) MiB (the device takes 64 MiB)"
    if ((tree + carried > 62 << 20)); then
        echo "too large for one device call: leave something out" >&2
        exit 1
    fi
}

device() {
    local small=0
    [[ "${1:-}" == "--small" ]] && small=1
    local out="${OUT:-$root/gpu-check-out}"
    mkdir -p "$out"
    local log="$out/gpu-check.log" table="$out/gpu-check.md"
    : >"$log"
    cd "$root"
    if ls .gl/*.deb >/dev/null 2>&1 && [[ $small == 0 ]]; then
        for f in .gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    fi
    if [[ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ]]; then
        export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
        export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    fi
    local work
    work=$(mktemp -d)
    tar -xJf "$pack/pack.tar.xz" -C "$work"
    local bin="$work/bin"
    {
        echo "# GPU check, $(date -u +%Y-%m-%dT%H:%MZ)"
        echo
        echo "- machine: $(nproc) CPU cores; $(nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>/dev/null || echo 'no nvidia-smi')"
        echo "- deepmorph $("$bin/deepmorph" --version 2>/dev/null | head -1), release, float32, backend wgpu"
        echo
    } >"$table"

    local size=512 sweeps=3 pre=2 bench_time=5 filter_energy='wgpu/C67'
    if [[ $small == 1 ]]; then
        size=64 sweeps=1 pre=1 bench_time=1 filter_energy='step/wgpu/C3/64'
    fi
    # 1. Benches (criterion; every iteration ends with device.sync()).
    echo "## Benches (criterion, median of 10 samples)" >>"$table"
    echo >>"$table"
    echo '```' >>"$table"
    local benches=("sweep:wgpu" "energy:$filter_energy")
    [[ $small == 1 ]] && benches=("sweep:sweep_K15/wgpu/64" "energy:$filter_energy")
    for b in "${benches[@]}"; do
        local name=${b%%:*} filter=${b#*:}
        (cd "$work" && timeout 120 "$bin/$name" --bench "$filter" --measurement-time "$bench_time" \
            --warm-up-time 1 --noplot 2>&1) | tee -a "$log" | grep -E '^[a-z_A-Z0-9/.-]+ *$|time: ' >>"$table" || true
    done
    echo '```' >>"$table"
    echo >>"$table"

    # 2. A deep morph of the faces pair at the paper's size, both schedules, a few sweeps a
    # level (every sweep run: no tolerance), with the time outside the solver.
    echo "## Deep morph, faces, ${size}², K = 15, 5 levels × $sweeps sweeps ($pre feature-only)" >>"$table"
    echo >>"$table"
    echo "| schedule | wall s | solver s | E final | how it ended | estimate printed |" >>"$table"
    echo "|---|---|---|---|---|---|" >>"$table"
    local a b
    a=$(ls "$bin"/a.* | head -1)
    b=$(ls "$bin"/b.* | head -1)
    for schedule in sequential batched; do
        local dir="$work/morph_$schedule" started ended status=0
        started=$(date +%s.%N)
        # At the timeout, SIGTERM: the run stops after its sweep and still writes its
        # outputs (exit 130), so the row shows how far it got.
        timeout 150 "$bin/deepmorph" morph "$a" "$b" -o "$dir" --backend wgpu --model deep \
            --vgg19 "$bin/vgg19_f16.safetensors" --quality paper --size "${size}x${size}" \
            --sweeps "$sweeps" --pre-sweeps "$pre" --schedule "$schedule" --video gif -v \
            >>"$log" 2>&1 || status=$?
        ended=$(date +%s.%N)
        [[ -f "$dir/config.json" ]] || echo "| $schedule | failed (exit $status): see the log | | | | |" >>"$table"
        if [[ -f "$dir/config.json" ]]; then
            python3 - "$dir" "$schedule" "$started" "$ended" "$log" >>"$table" <<'EOF'
import json, sys, re
d, schedule, started, ended, log = sys.argv[1:]
record = json.load(open(d + "/config.json"))
rows = open(d + "/energy.csv").read().strip().splitlines()
energy = rows[-1].split(",")[4]
estimate = ""
for line in open(log):
    m = re.search(r"estimated time: (.*)", line)
    if m:
        estimate = m.group(1).strip()
outcome = record["outcome"]
print(f"| {schedule} | {float(ended) - float(started):.1f} | {outcome['seconds']:.1f} | {energy} | {outcome['termination']} | {estimate} |")
EOF
        fi
    done
    echo >>"$table"
    cat "$table"
    rm -rf "$work"
}

case "${1:-}" in
prepare) prepare ;;
device)
    shift
    device "$@"
    ;;
*)
    echo "usage: scripts/gpu-check.sh prepare | device [--small]" >&2
    exit 2
    ;;
esac
