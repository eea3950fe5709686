#!/usr/bin/env python3
"""The peer benchmark's measuring half (scripts/bench-peer.sh sets up and calls it).

For each volume it renders the same picture with VTK's vtkGPUVolumeRayCastMapper (the mapper
3D Slicer and SlicerVirtualReality render with) and with cao-xr's ray caster, and times both,
interleaved in one invocation:

  VTK     one process, one render window; after a warm-up render (texture upload, shader
          compile), --frames Render() calls, each followed by glFinish (WaitForCompletion), the
          camera turned by +-0.05 degrees between them so that nothing can be reused; a round's
          figure is the median of its frames.
  cao-xr  `cao-xr render VOLUME --no-ao --shading phong` at SIZE and at 16x16, each a fresh
          process timed by wall clock; (full - tiny) / 2 is the ray cast of one eye (render draws
          both eyes; the setup both sizes share: start-up, volume load, the unused AO precompute
          at its cheapest, K = 6, M = 1, cancels). What is left also holds reading back and
          writing the 16x16 -> SIZE PNGs (a few tens of ms).

Rounds alternate VTK, cao-xr, VTK, cao-xr, ...; the table gives the median over rounds (and the
range). Same volume, image size (square), sample step in mm (cao-xr's default: half the
smallest spacing), transfer function (cao-xr's JSON format, opacity per 1 mm, given to VTK with
ScalarOpacityUnitDistance = 1 mm), Blinn-Phong weights (ka, kd, ks, p = 0.3, 0.75, 0.2, 24) with a
headlight, trilinear interpolation, jittered ray starts, no ambient occlusion, and cao-xr's left
eye framing (its default stereo views) reproduced with an off-axis VTK camera.
"""

import argparse
import gzip
import json
import math
import os
import re
import statistics
import subprocess
import sys
import time

import numpy as np

# cao-xr's `ct-bone` preset (src/volume/transfer.rs, TransferFunction::preset), its default for
# CT: control points on Hounsfield units, linear RGB, alpha = opacity per 1 mm of path. Written as
# a JSON file that both renderers get, so that both see exactly the same function.
CT_BONE = {
    "name": "ct-bone",
    "domain": "data",
    "points": [
        {"value": -1024.0, "color": [0.0, 0.0, 0.0], "alpha": 0.0},
        {"value": 150.0, "color": [0.80, 0.55, 0.40], "alpha": 0.0},
        {"value": 350.0, "color": [0.80, 0.55, 0.40], "alpha": 0.25},
        {"value": 700.0, "color": [0.93, 0.89, 0.80], "alpha": 0.8},
        {"value": 1500.0, "color": [1.0, 0.98, 0.94], "alpha": 0.95},
        {"value": 4000.0, "color": [1.0, 1.0, 1.0], "alpha": 1.0},
    ],
}

# src/render/mod.rs: PHONG (ka, kd, ks, shininess), STEP_PER_SPACING, the default background.
PHONG = (0.3, 0.75, 0.2, 24.0)
STEP_PER_SPACING = 0.5
BACKGROUND = (0.06, 0.07, 0.09)
# src/space.rs: DEFAULT_IPD (m) and default_stereo_views' framing.
IPD_MM = 64.0
TINY = 16


def log(msg):
    print(msg, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Volumes: geometry as cao-xr reads it (`cao-xr info`), voxels read here.


def cao_info(binary, path):
    out = subprocess.run([binary, "info", path], check=True, capture_output=True, text=True).stdout
    info = {}
    m = re.search(r"^dims\s+(\d+) x (\d+) x (\d+)", out, re.M)
    info["dims"] = [int(g) for g in m.groups()]
    m = re.search(r"^spacing\s+([\d.]+) x ([\d.]+) x ([\d.]+)", out, re.M)
    info["spacing"] = [float(g) for g in m.groups()]
    m = re.search(r"^directions\s+i DVec3\(([^)]*)\)\s+j DVec3\(([^)]*)\)\s+k DVec3\(([^)]*)\)", out, re.M)
    info["directions"] = [[float(x) for x in g.split(",")] for g in m.groups()]
    m = re.search(r"^name\s+(.*)$", out, re.M)
    info["name"] = m.group(1).strip()
    return info


NRRD_TYPES = {
    "int8": "i1", "signed char": "i1", "uint8": "u1", "uchar": "u1", "unsigned char": "u1",
    "int16": "i2", "short": "i2", "signed short": "i2", "uint16": "u2", "ushort": "u2",
    "unsigned short": "u2", "int32": "i4", "int": "i4", "uint32": "u4", "float": "f4", "double": "f8",
}
NIFTI_TYPES = {2: "u1", 4: "i2", 8: "i4", 16: "f4", 64: "f8", 256: "i1", 512: "u2", 768: "u4"}


def read_nrrd(path):
    with open(path, "rb") as f:
        raw = f.read()
    head, _, body = raw.partition(b"\n\n")
    fields = {}
    for line in head.decode("latin-1").splitlines()[1:]:
        if line.startswith("#") or ":" not in line:
            continue
        k, _, v = line.partition(":")
        fields[k.strip().lower()] = v.lstrip("=").strip()
    if "data file" in fields or "datafile" in fields:
        raise SystemExit(f"{path}: detached NRRD data is not supported here")
    dt = NRRD_TYPES[fields["type"]]
    endian = "<" if fields.get("endian", "little") == "little" else ">"
    enc = fields.get("encoding", "raw")
    if enc in ("gzip", "gz"):
        body = gzip.decompress(body)
    elif enc != "raw":
        raise SystemExit(f"{path}: NRRD encoding {enc} is not supported here")
    sizes = [int(s) for s in fields["sizes"].split()]
    n = int(np.prod(sizes))
    a = np.frombuffer(body[len(body) - n * np.dtype(dt).itemsize:], dtype=endian + dt)
    return a.reshape(sizes[::-1])


def read_nifti(path):
    op = gzip.open if path.endswith(".gz") else open
    with op(path, "rb") as f:
        raw = f.read()
    endian = "<" if int.from_bytes(raw[0:4], "little") == 348 else ">"
    if int.from_bytes(raw[0:4], "little" if endian == "<" else "big") != 348:
        raise SystemExit(f"{path}: only NIfTI-1 is supported here")
    dim = np.frombuffer(raw[40:56], dtype=endian + "i2")
    datatype = int(np.frombuffer(raw[70:72], dtype=endian + "i2")[0])
    vox_offset = int(np.frombuffer(raw[108:112], dtype=endian + "f4")[0])
    slope, inter = np.frombuffer(raw[112:120], dtype=endian + "f4")
    sizes = [int(d) for d in dim[1:4]]
    dt = np.dtype(endian + NIFTI_TYPES[datatype])
    n = int(np.prod(sizes))
    a = np.frombuffer(raw[vox_offset:vox_offset + n * dt.itemsize], dtype=dt).reshape(sizes[::-1])
    if slope not in (0.0, 1.0) or inter != 0.0:
        a = a.astype(np.float32) * (slope if slope != 0.0 else 1.0) + inter
    return a


def load_lps(binary, path):
    """The voxels as an array [z][y][x] whose index axes run along +L, +P, +S (axis-aligned
    orientations only: each index axis is flipped and permuted onto its LPS axis), with the
    spacing along L, P, S."""
    info = cao_info(binary, path)
    if path.endswith(".nrrd"):
        a = read_nrrd(path)
    elif path.endswith(".nii") or path.endswith(".nii.gz"):
        a = read_nifti(path)
    else:
        raise SystemExit(f"{path}: give a .nrrd or .nii(.gz) file")
    if list(a.shape[::-1]) != info["dims"]:
        raise SystemExit(f"{path}: read {a.shape[::-1]}, cao-xr reads {info['dims']}")
    a = a.transpose(2, 1, 0)  # [i][j][k]
    axes, spacing = [None] * 3, [None] * 3
    for idx, d in enumerate(info["directions"]):
        b = int(np.argmax(np.abs(d)))
        if abs(abs(d[b]) - 1.0) > 1e-3:
            raise SystemExit(f"{path}: oblique orientation {info['directions']} is not supported here")
        if d[b] < 0:
            a = np.flip(a, axis=idx)
        axes[b], spacing[b] = idx, info["spacing"][idx]
    a = np.ascontiguousarray(a.transpose(axes).transpose(2, 1, 0))  # [S][P][L]
    return info, a, spacing


# ---------------------------------------------------------------------------------------------
# cao-xr's left eye, as src/space.rs places it (world: L -> +X, S -> +Y, anterior -> +Z).


def framing(dims, spacing):
    ext = [n * s for n, s in zip(dims, spacing)]
    r = 0.5 * math.sqrt(sum(e * e for e in ext)) * 1.02  # mm, bounding_radius * 1.02
    dist = max(2.6 * r, 300.0)
    return r, dist


# ---------------------------------------------------------------------------------------------
# VTK


class VtkScene:
    def __init__(self, arr, spacing, tf, step, size, jitter=True):
        import vtk
        from vtk.util import numpy_support

        self.vtk = vtk
        nz, ny, nx = arr.shape
        img = vtk.vtkImageData()
        img.SetDimensions(nx, ny, nz)
        img.SetSpacing(*spacing)
        # centred at the origin: the centre of the voxel centres, as cao-xr's box is centred
        img.SetOrigin(*[-0.5 * (n - 1) * s for n, s in zip((nx, ny, nz), spacing)])
        scal = numpy_support.numpy_to_vtk(arr.ravel(), deep=True)
        scal.SetName("scalars")
        img.GetPointData().SetScalars(scal)
        self.image = img

        color = vtk.vtkColorTransferFunction()
        opacity = vtk.vtkPiecewiseFunction()
        for p in tf["points"]:
            color.AddRGBPoint(p["value"], *p["color"])
            opacity.AddPoint(p["value"], p["alpha"])
        prop = vtk.vtkVolumeProperty()
        prop.SetColor(color)
        prop.SetScalarOpacity(opacity)
        prop.SetScalarOpacityUnitDistance(1.0)  # alpha is opacity per 1 mm
        prop.SetInterpolationTypeToLinear()
        prop.ShadeOn()
        prop.SetAmbient(PHONG[0])
        prop.SetDiffuse(PHONG[1])
        prop.SetSpecular(PHONG[2])
        prop.SetSpecularPower(PHONG[3])

        mapper = vtk.vtkGPUVolumeRayCastMapper()
        mapper.SetInputData(img)
        mapper.SetBlendModeToComposite()
        mapper.SetAutoAdjustSampleDistances(0)
        mapper.SetLockSampleDistanceToInputSpacing(0)
        mapper.SetSampleDistance(step)
        mapper.SetImageSampleDistance(1.0)
        mapper.SetUseJittering(1 if jitter else 0)
        volume = vtk.vtkVolume()
        volume.SetMapper(mapper)
        volume.SetProperty(prop)

        ren = vtk.vtkRenderer()
        ren.SetBackground(*BACKGROUND)
        ren.AutomaticLightCreationOff()
        light = vtk.vtkLight()
        light.SetLightTypeToHeadlight()
        ren.AddLight(light)
        ren.AddVolume(volume)
        rw = vtk.vtkRenderWindow()
        rw.SetOffScreenRendering(1)
        rw.SetMultiSamples(0)
        rw.SetSize(size, size)
        rw.AddRenderer(ren)
        self.ren, self.rw, self.mapper = ren, rw, mapper

    def set_left_eye(self, dims, spacing):
        """cao-xr's left eye: 32 mm to the viewer's left (the patient's right, -L), parallel to
        the other eye, looking at the patient's face (along +P), superior up; the asymmetric
        frustum that frames the bounding sphere (+-r at the centre's depth) is VTK's symmetric
        one of half-angle atan(r / dist) with its window centre shifted."""
        r, dist = framing(dims, spacing)
        x = -0.5 * IPD_MM
        cam = self.ren.GetActiveCamera()
        cam.SetPosition(x, -dist, 0.0)
        cam.SetFocalPoint(x, 0.0, 0.0)
        cam.SetViewUp(0.0, 0.0, 1.0)
        cam.SetViewAngle(2.0 * math.degrees(math.atan(r / dist)))
        cam.SetWindowCenter(-x / r, 0.0)
        cam.SetClippingRange(max(1.0, dist - 1.2 * r), dist + 1.2 * r)
        self.camera = cam

    def render(self):
        self.rw.Render()
        self.rw.WaitForCompletion()

    def time_frames(self, frames):
        """Seconds of each of `frames` renders, the camera turned by +-0.05 degrees between them
        (it comes back to where it was after an even number)."""
        times = []
        for f in range(frames):
            self.camera.Azimuth(0.05 if f % 2 == 0 else -0.05)
            t = time.perf_counter()
            self.render()
            times.append(time.perf_counter() - t)
        if frames % 2:
            self.camera.Azimuth(-0.05)
        return times

    def picture(self):
        """RGB uint8 rows top to bottom."""
        vtk = self.vtk
        from vtk.util import numpy_support

        self.render()
        w2i = vtk.vtkWindowToImageFilter()
        w2i.SetInput(self.rw)
        w2i.SetInputBufferTypeToRGB()
        w2i.ReadFrontBufferOff()
        w2i.Update()
        out = w2i.GetOutput()
        w, h, _ = out.GetDimensions()
        a = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)
        return np.ascontiguousarray(a[::-1, :, :3])

    def gl_renderer(self):
        caps = self.rw.ReportCapabilities()
        m = re.search(r"OpenGL renderer string:\s*(.*)", caps)
        return m.group(1).strip() if m else "?"

    def close(self):
        self.rw.Finalize()


def write_png(path, rgb):
    import vtk
    from vtk.util import numpy_support

    h, w, c = rgb.shape
    img = vtk.vtkImageData()
    img.SetDimensions(w, h, 1)
    arr = numpy_support.numpy_to_vtk(np.ascontiguousarray(rgb[::-1]).reshape(-1, c), deep=True)
    img.GetPointData().SetScalars(arr)
    wr = vtk.vtkPNGWriter()
    wr.SetFileName(path)
    wr.SetInputData(img)
    wr.Write()


def read_png(path):
    import vtk
    from vtk.util import numpy_support

    rd = vtk.vtkPNGReader()
    rd.SetFileName(path)
    rd.Update()
    out = rd.GetOutput()
    w, h, _ = out.GetDimensions()
    a = numpy_support.vtk_to_numpy(out.GetPointData().GetScalars()).reshape(h, w, -1)
    return np.ascontiguousarray(a[::-1, :, :3])


def label_strip(width, text, height=30):
    """A strip of the background colour with `text` centred on it (VTK's own text renderer)."""
    import vtk
    from vtk.util import numpy_support

    strip = np.zeros((height, width, 3), dtype=np.float32)
    strip[:] = [c * 255 for c in BACKGROUND]
    tp = vtk.vtkTextProperty()
    tp.SetFontFamilyToArial()
    tp.SetFontSize(13)
    img, dims = vtk.vtkImageData(), [0, 0]
    if not vtk.vtkTextRenderer().RenderString(tp, text, img, dims, 96):
        return strip.astype(np.uint8)
    w, h, _ = img.GetDimensions()
    rgba = numpy_support.vtk_to_numpy(img.GetPointData().GetScalars()).reshape(h, w, 4)
    tw, th = min(dims[0], width), min(dims[1], height)
    a = (rgba[:th, :tw, 3:4].astype(np.float32) / 255.0)[::-1]
    x0, y0 = (width - tw) // 2, (height - th) // 2
    region = strip[y0:y0 + th, x0:x0 + tw]
    strip[y0:y0 + th, x0:x0 + tw] = region * (1 - a) + 225.0 * a
    return np.clip(strip + 0.5, 0, 255).astype(np.uint8)


def coverage(rgb):
    """Pixels where something was drawn: off the background by more than 3/255 in a channel."""
    bg = np.array([round(c * 255) for c in BACKGROUND], dtype=np.int16)
    return (np.abs(rgb.astype(np.int16) - bg).max(axis=2) > 3)


# ---------------------------------------------------------------------------------------------
# cao-xr


def cao_render(binary, path, tf_json, size, out_dir):
    cmd = [binary, "render", path, "--tf", tf_json, "--no-ao", "--shading", "phong",
           # the AO volume is computed but unused with --no-ao: at its cheapest
           "--rays", "6", "--steps", "1",
           "--size", f"{size}x{size}", "--out", out_dir]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if p.returncode != 0:
        raise SystemExit(f"cao-xr render failed ({' '.join(cmd)}):\n{p.stderr}{p.stdout}")
    gpu = re.search(r"^GPU: (.*)$", p.stderr + p.stdout, re.M)
    return wall, (gpu.group(1) if gpu else "?")


def cao_psnr(binary, a, b):
    p = subprocess.run([binary, "compare", a, b], capture_output=True, text=True)
    m = re.search(r"PSNR ([\d.inf-]+) dB\s+SSIM ([\d.]+)", p.stdout)
    return (float(m.group(1)), float(m.group(2))) if m else (float("nan"), float("nan"))


# ---------------------------------------------------------------------------------------------


def med(xs):
    return statistics.median(xs)


def bench_volume(args, label, path, tf, tf_json):
    info, arr, spacing = load_lps(args.cao_xr, path)
    step = STEP_PER_SPACING * min(info["spacing"])
    dims_lps = list(arr.shape[::-1])
    vdir = os.path.join(args.out, label)
    os.makedirs(vdir, exist_ok=True)
    log(f"{label}: {path}, {'x'.join(map(str, info['dims']))} voxels of "
        f"{' x '.join(f'{s:.4g}' for s in info['spacing'])} mm, step {step:.4g} mm")

    scene = VtkScene(arr, spacing, tf, step, args.size, jitter=True)
    scene.set_left_eye(dims_lps, spacing)
    t = time.perf_counter()
    scene.render()  # warm-up: texture upload, shader compile
    warm = time.perf_counter() - t
    gl = scene.gl_renderer()
    log(f"  VTK on {gl}: first render {warm:.2f} s")

    vtk_rounds, cao_rounds, cao_raw = [], [], []
    vk = "?"
    for r in range(args.rounds):
        times = scene.time_frames(args.frames)
        vtk_rounds.append(med(times))
        full, vk = cao_render(args.cao_xr, path, tf_json, args.size, os.path.join(vdir, "cao-xr"))
        tiny, _ = cao_render(args.cao_xr, path, tf_json, TINY, os.path.join(vdir, "cao-xr-tiny"))
        cao_rounds.append(0.5 * (full - tiny))
        cao_raw.append((full, tiny))
        log(f"  round {r + 1}/{args.rounds}: VTK {vtk_rounds[-1]:.3f} s/frame "
            f"(frames {', '.join(f'{x:.3f}' for x in times)}); cao-xr {cao_rounds[-1]:.3f} s/eye "
            f"({args.size}: {full:.2f} s, {TINY}: {tiny:.2f} s)")

    vtk_pic = scene.picture()
    scene.close()
    cao_pic = read_png(os.path.join(vdir, "cao-xr", "left.png"))
    vtk_png = os.path.join(vdir, "vtk.png")
    cao_png = os.path.join(vdir, "cao-xr.png")
    write_png(vtk_png, vtk_pic)
    write_png(cao_png, cao_pic)
    gap = np.zeros((args.size, 8, 3), dtype=np.uint8)
    gap[:] = [round(c * 255) for c in BACKGROUND]
    import vtk

    vtk_s, cao_s = med(vtk_rounds), med(cao_rounds)
    top = np.concatenate([
        label_strip(args.size, f"cao-xr ray cast, left eye: {cao_s:.2f} s per eye"),
        gap[:30],
        label_strip(args.size, f"VTK {vtk.vtkVersion.GetVTKVersion()} GPU ray cast: {vtk_s:.2f} s per frame"),
    ], axis=1)
    side = os.path.join(vdir, "side-by-side.png")
    write_png(side, np.concatenate([top, np.concatenate([cao_pic, gap, vtk_pic], axis=1)], axis=0))
    cv, cc = coverage(vtk_pic), coverage(cao_pic)
    psnr, ssim = cao_psnr(args.cao_xr, cao_png, vtk_png)
    row = {
        "volume": label,
        "path": path,
        "dims": info["dims"],
        "spacing_mm": info["spacing"],
        "step_mm": step,
        "size": args.size,
        "gl_renderer": gl,
        "vulkan_device": vk,
        "vtk_s_per_frame": med(vtk_rounds),
        "vtk_rounds": vtk_rounds,
        "cao_s_per_eye": med(cao_rounds),
        "cao_rounds": cao_rounds,
        "cao_wall_full_tiny": cao_raw,
        "ratio": med(cao_rounds) / med(vtk_rounds),
        "covered_vtk": float(cv.mean()),
        "covered_cao": float(cc.mean()),
        "covered_both": float((cv & cc).mean()),
        "covered_either": float((cv | cc).mean()),
        "psnr_db": psnr,
        "ssim": ssim,
        "side_by_side": side,
    }
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cao-xr", required=True, help="the cao-xr binary")
    ap.add_argument("--out", default="/tmp/bench-peer")
    ap.add_argument("--size", type=int, default=512, help="pixels per side (square)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds (VTK, cao-xr) per volume")
    ap.add_argument("--frames", type=int, default=5, help="timed VTK renders per round")
    ap.add_argument("--backend", default="", help="what the GL window runs on, for the report")
    ap.add_argument("volumes", nargs="+", help="LABEL=PATH (.nrrd or .nii)")
    args = ap.parse_args()
    os.makedirs(args.out, exist_ok=True)
    tf_json = os.path.join(args.out, "ct-bone.json")
    with open(tf_json, "w") as f:
        json.dump(CT_BONE, f, indent=1)

    rows = []
    for spec in args.volumes:
        label, _, path = spec.partition("=")
        rows.append(bench_volume(args, label, path, CT_BONE, tf_json))
    with open(os.path.join(args.out, "results.json"), "w") as f:
        json.dump(rows, f, indent=1)

    n = args.size
    print()
    print(f"Peer benchmark, {n}x{n}, TF ct-bone (opacity per 1 mm), Phong (0.3, 0.75, 0.2, 24), "
          f"headlight, no AO, cao-xr's default step (half the smallest spacing).")
    print(f"VTK {__import__('vtk').vtkVersion.GetVTKVersion()} vtkGPUVolumeRayCastMapper on "
          f"{rows[0]['gl_renderer']} ({args.backend or 'offscreen'}); cao-xr on {rows[0]['vulkan_device']}.")
    print(f"Medians of {args.rounds} interleaved rounds (VTK, cao-xr, VTK, ...): VTK s per frame = "
          f"median of {args.frames} Render() + glFinish after a warm-up, the camera turned 0.05 deg "
          f"between them; cao-xr s per eye = (wall of `render --no-ao` at {n}x{n} - the same at "
          f"{TINY}x{TINY}) / 2 eyes.")
    hdr = (f"{'volume':<18} {'voxels':<13} {'step mm':>7} {'VTK s/frame':>12} {'cao-xr s/eye':>13} "
           f"{'cao-xr/VTK':>10} {'covered VTK/cao/both':>21} {'PSNR dB':>8}")
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        rng = lambda xs: f"{min(xs):.2f}-{max(xs):.2f}"
        print(f"{r['volume']:<18} {'x'.join(map(str, r['dims'])):<13} {r['step_mm']:>7.3f} "
              f"{r['vtk_s_per_frame']:>12.3f} {r['cao_s_per_eye']:>13.3f} {r['ratio']:>9.2f}x "
              f"{100 * r['covered_vtk']:>6.1f}/{100 * r['covered_cao']:.1f}/{100 * r['covered_both']:.1f} % "
              f"{r['psnr_db']:>8.2f}")
        print(f"{'':<18} ranges over rounds: VTK {rng(r['vtk_rounds'])} s, cao-xr {rng(r['cao_rounds'])} s")
    print("PSNR (luma, `cao-xr compare`) is for information only: different renderers "
          "(cao-xr pre-integrates, VTK point-samples; different gradients and jitter).")
    for r in rows:
        print(f"{r['volume']}: {r['side_by_side']} (left: cao-xr's left eye, right: VTK)")


if __name__ == "__main__":
    main()
