"""Writes a volume and a 3D Slicer segmentation of overlapping segments with pynrrd, as Slicer
writes them: a 4-D .seg.nrrd whose first axis is the layer (kind `list`, space direction
`none`), on a box cropped out of the volume's grid, with the SegmentN_* fields. Prints, as
JSON, each segment's voxel count in the volume's grid from pynrrd's own reading of the file,
under cao-xr's rule for overlaps (the segment of fewer voxels wins).

usage: write_seg_nrrd.py DIR
"""
import json
import sys

import nrrd
import numpy as np

out = sys.argv[1]
spacing = np.array([1.5, 1.2, 2.0])
dims = (20, 18, 16)
lps = np.diag(spacing)
origin = np.array([-10.0, 4.0, 30.0])
volume = np.full(dims, -1000, dtype=np.int16)
volume[2:18, 2:16, 2:14] = 60
nrrd.write(f"{out}/volume.nrrd", volume, {
    "space": "left-posterior-superior",
    "space directions": lps,
    "space origin": origin,
    "kinds": ["domain"] * 3,
}, index_order="F")

# The segmentation covers voxels [3, 17) x [2, 16) x [1, 15) of the volume.
lo = np.array([3, 2, 1])
box = (14, 14, 14)
ix, iy, iz = np.meshgrid(*[np.arange(n) for n in box], indexing="ij")
layers = np.zeros((2,) + box, dtype=np.uint8)
liver = (ix >= 1) & (ix < 12) & (iy >= 1) & (iy < 12) & (iz >= 2) & (iz < 12)
vein = (np.hypot(ix - 12.0, iy - 6.0) < 1.5) & ~liver
tumour = ((ix - 6.0) ** 2 + (iy - 6.0) ** 2 + (iz - 7.0) ** 2) < 9.0
layers[0][liver] = 1
layers[0][vein] = 2
layers[1][tumour] = 1
segments = [
    # name, layer, value, colour
    ("liver", 0, 1, "0.86 0.49 0.38"),
    ("portal vein", 0, 2, "0.0 0.59 0.81"),
    ("tumour", 1, 1, "0.8 0.8 0.2"),
]
header = {
    "space": "left-posterior-superior",
    "space directions": np.vstack([np.full(3, np.nan), lps]),
    "space origin": origin + lps @ lo,
    "kinds": ["list", "domain", "domain", "domain"],
    "encoding": "gzip",
}
for n, (name, layer, value, colour) in enumerate(segments):
    header[f"Segment{n}_Color"] = colour
    header[f"Segment{n}_ID"] = f"Segment_{n + 1}"
    header[f"Segment{n}_LabelValue"] = str(value)
    header[f"Segment{n}_Layer"] = str(layer)
    header[f"Segment{n}_Name"] = name
nrrd.write(f"{out}/overlap.seg.nrrd", layers, header, index_order="F")

# pynrrd's own reading, painted into the volume's grid, largest segment first.
data, h = nrrd.read(f"{out}/overlap.seg.nrrd", index_order="F")
assert data.shape == (2,) + box
masks = {}
for n, (name, layer, value, _) in enumerate(segments):
    m = np.zeros(dims, dtype=bool)
    m[lo[0]:lo[0] + box[0], lo[1]:lo[1] + box[1], lo[2]:lo[2] + box[2]] = data[layer] == value
    masks[name] = m
combined = np.full(dims, "", dtype=object)
for name in sorted(masks, key=lambda k: -masks[k].sum()):
    combined[masks[name]] = name
print(json.dumps({name: int((combined == name).sum()) for name in masks}))
