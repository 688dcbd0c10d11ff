#!/usr/bin/env python3
"""Joins the benchmarks of scripts/gpu-check.sh into one JSON and one Markdown table.

Reads RESULTS/{sort,splat,composite,avatar}.json (each `engine-bench ... --json`),
RESULTS/train-profile.json, train-profile.txt and train-args.txt (`drape train
--profile`). Fails, naming the file and the field, when a benchmark's output lacks a
figure the table needs: a renamed field must not give an empty table. Standard library
only (the lent machine has Python but nothing can be installed there).
"""

import argparse
import datetime
import json
import pathlib
import sys


def fail(msg):
    print(f"gpu-check-report: {msg}", file=sys.stderr)
    sys.exit(1)


def load(results, name):
    path = results / name
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        fail(f"{path}: {e}")


def need(obj, key, where):
    if not isinstance(obj, dict) or key not in obj:
        fail(f"{where}: no field '{key}'")
    return obj[key]


def ms(v):
    return f"{v:.2f}" if isinstance(v, (int, float)) else "n/a"


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("results", type=pathlib.Path)
    ap.add_argument("--commit", required=True)
    ap.add_argument("--mode", required=True)
    ap.add_argument("--json", type=pathlib.Path, required=True)
    ap.add_argument("--markdown", type=pathlib.Path, required=True)
    a = ap.parse_args()

    sort = load(a.results, "sort.json")
    splat = load(a.results, "splat.json")
    composite = load(a.results, "composite.json")
    avatar = load(a.results, "avatar.json")
    profile = load(a.results, "train-profile.json")
    profile_txt = (a.results / "train-profile.txt").read_text()
    train_args = (a.results / "train-args.txt").read_text().split()
    device = need(sort, "device", "sort.json")

    md = [
        f"# gpu-check on {device}",
        "",
        f"Commit `{a.commit}`, mode `{a.mode}`, "
        f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC. "
        "Medians; GPU ms from timestamp queries.",
        "",
        "## Sort (radix, u32 pairs)",
        "",
        "| keys | GPU ms | wall ms | keys/s | verified |",
        "|---:|---:|---:|---:|---|",
        f"| {need(sort, 'n', 'sort.json'):,} | {ms(need(sort, 'gpu_median_ms', 'sort.json'))} "
        f"| {ms(need(sort, 'median_ms', 'sort.json'))} "
        f"| {need(sort, 'keys_per_s', 'sort.json'):.3g} | {need(sort, 'verified', 'sort.json')} |",
        "",
        "## Splat (random Gaussians, SH 3)",
        "",
        "| scene | forward ms | forward FPS | fwd+bwd ms | fwd+bwd FPS |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in need(splat, "results", "splat.json"):
        w = "splat.json results[]"
        md.append(
            f"| {need(r, 'config', w)} | {ms(need(r, 'forward_median_ms', w))} "
            f"| {need(r, 'forward_fps', w):.1f} | {ms(need(r, 'forward_backward_median_ms', w))} "
            f"| {need(r, 'forward_backward_fps', w):.1f} |"
        )
    g = need(composite, "gaussians", "composite.json")
    md += [
        "",
        f"## Composite (body {need(g, 'body', 'composite.json gaussians'):,}, cloth {need(g, 'cloth', 'composite.json gaussians'):,}, scene {need(g, 'scene', 'composite.json gaussians'):,} Gaussians)",
        "",
        "| size | three passes, serialised ms | overlapped ms | fused ms | one pass ms |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in need(composite, "results", "composite.json"):
        w = "composite.json results[]"
        cell = lambda k: ms(need(need(r, k, w), "forward_median_ms", f"{w}.{k}"))  # noqa: E731
        md.append(
            f"| {need(r, 'width', w)}x{need(r, 'height', w)} | {cell('three_pass_serialised')} "
            f"| {cell('three_pass_overlapped')} | {cell('fused')} | {cell('one_pass')} |"
        )
    md += [
        "",
        f"## Avatar (`{pathlib.Path(need(avatar, 'run', 'avatar.json')).name}`, "
        f"Gaussians {need(avatar, 'gaussians', 'avatar.json')})",
        "",
        "| size | compositing | frame ms | FPS | dispatches | barriers | decoders | skinning | projection | sorts | raster | composite |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in need(avatar, "render", "avatar.json"):
        w = "avatar.json render[]"
        st = need(r, "stages_gpu_ms", w)
        stage = lambda *names: ms(next((st[n] for n in names if n in st), None))  # noqa: E731
        md.append(
            f"| {need(r, 'width', w)}x{need(r, 'height', w)} | {need(r, 'compositing', w)} "
            f"| {ms(need(r, 'frame_median_ms', w))} | {need(r, 'fps', w):.1f} "
            f"| {need(r, 'dispatches_per_frame', w)} | {need(r, 'barriers_per_frame', w)} "
            f"| {stage('decoders')} | {stage('skinning')} | {stage('projection')} "
            f"| {stage('sorts', 'binning and sorts')} | {stage('rasterization')} | {stage('composite')} |"
        )
    flight = need(avatar, "frames_in_flight", "avatar.json")
    if isinstance(flight, dict):
        md += [
            "",
            f"Library frames (`AvatarPlayer`) at {need(flight, 'width', 'avatar.json frames_in_flight')}x{need(flight, 'height', 'avatar.json frames_in_flight')}:",
            "",
            "| in flight | FPS | fence waits while submitting | device memory, loaded | with frames |",
            "|---:|---:|---:|---:|---:|",
        ]
        for s in need(flight, "settings", "avatar.json frames_in_flight"):
            w = "avatar.json frames_in_flight.settings[]"
            mib = lambda k: f"{need(s, k, w) / 2**20:.1f} MiB"  # noqa: E731
            md.append(
                f"| {need(s, 'frames_in_flight', w)} | {need(s, 'fps', w):.1f} "
                f"| {need(s, 'fence_waits_while_submitting', w)} of {need(s, 'frames', w)} "
                f"| {mib('device_memory_loaded_bytes')} | {mib('device_memory_with_frames_bytes')} |"
            )
    tr = need(avatar, "training", "avatar.json")
    if isinstance(tr, dict):
        md += [
            "",
            f"Training the run's own config ({tr.get('compositing')}): "
            f"{ms(need(tr, 'ms_per_step', 'avatar.json training'))} ms/step, "
            f"{need(tr, 'iterations_per_second', 'avatar.json training'):.2f} it/s.",
        ]
    head = profile_txt.splitlines()[0] if profile_txt.strip() else fail("train-profile.txt is empty")
    md += [
        "",
        f"## Training step (`drape train {' '.join(train_args)} --profile`)",
        "",
        head,
        "",
        "```",
        *profile_txt.splitlines()[1:40],
        "```",
        "",
    ]

    report = {
        "device": device,
        "commit": a.commit,
        "mode": a.mode,
        "sort": sort,
        "splat": splat,
        "composite": composite,
        "avatar": avatar,
        "train": {"args": train_args, "summary": head, "profile": profile},
    }
    a.json.write_text(json.dumps(report, indent=1) + "\n")
    a.markdown.write_text("\n".join(md))


if __name__ == "__main__":
    main()
