"""Writes, with pydicom and highdicom, a CT series (ct/) and DICOM SEG objects of two segments on
another grid (the geometry of the series in coarse/: 2 x 2.5 x 4 mm, shifted, cropped), binary
and fractional (with a 0.3 shell that is outside), and prints highdicom's own reading of the
binary one resampled into the CT's grid by position (the nearest segmentation voxel to each CT
voxel's centre; the smaller segment where they overlap): the CT voxels of each segment.
Used by tests/integration/labels.rs."""
import json, os, sys
import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid
import highdicom as hd
from pydicom.sr.codedict import codes

out = sys.argv[1]
study, frame_of_ref = generate_uid(), generate_uid()

def series(folder, dims, spacing, origin, value):
    """A CT series of dims (cols, rows, slices) with pixel spacing spacing[0..2] (mm, x y z)."""
    uid = generate_uid()
    os.makedirs(folder, exist_ok=True)
    sets = []
    for k in range(dims[2]):
        fm = FileMetaDataset()
        fm.MediaStorageSOPClassUID = pydicom.uid.CTImageStorage
        fm.MediaStorageSOPInstanceUID = generate_uid()
        fm.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = fm
        ds.SOPClassUID = fm.MediaStorageSOPClassUID
        ds.SOPInstanceUID = fm.MediaStorageSOPInstanceUID
        ds.Modality = "CT"
        ds.PatientName, ds.PatientID, ds.PatientBirthDate, ds.PatientSex = "Seg^Test", "SEG1", "19700101", "O"
        ds.StudyInstanceUID, ds.StudyID, ds.StudyDate, ds.StudyTime = study, "1", "20260101", "120000"
        ds.AccessionNumber, ds.ReferringPhysicianName = "1", ""
        ds.SeriesInstanceUID, ds.SeriesNumber, ds.InstanceNumber = uid, 1, k + 1
        ds.FrameOfReferenceUID, ds.PositionReferenceIndicator = frame_of_ref, ""
        ds.Manufacturer = "test"
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.ImagePositionPatient = [origin[0], origin[1], origin[2] + k * spacing[2]]
        ds.PixelSpacing = [spacing[1], spacing[0]]
        ds.SliceThickness = spacing[2]
        ds.Rows, ds.Columns = dims[1], dims[0]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.RescaleIntercept, ds.RescaleSlope = 0, 1
        ds.PixelData = value(k).astype("<i2").tobytes()
        ds.save_as(os.path.join(folder, f"{k:03d}.dcm"), enforce_file_format=True)
        sets.append(ds)
    return sets

def centres(dims, spacing, origin):
    x, y, z = np.meshgrid(*[np.arange(d) for d in dims], indexing="ij")
    return np.stack([origin[0] + x * spacing[0], origin[1] + y * spacing[1], origin[2] + z * spacing[2]], -1)

# The CT: 40 x 36 x 24 at 1 x 1 x 2 mm; a soft ball with a dense core.
cd, cs, co = (40, 36, 24), (1.0, 1.0, 2.0), (-20.0, -18.0, 0.0)
P = centres(cd, cs, co)
r = np.linalg.norm(P - np.array([0.0, 0.0, 24.0]), axis=-1)
ct = np.where(r < 14, 60, -1000) + np.where(r < 5, 1140, 0)
series(os.path.join(out, "ct"), cd, cs, co, lambda k: ct[:, :, k].T)
# The segmentation's own grid: 2 x 2.5 x 4 mm, shifted, cropped (only its source images' geometry).
sd, ss, so = (20, 13, 12), (2.0, 2.5, 4.0), (-19.3, -15.6, 1.2)
Q = centres(sd, ss, so)
src = series(os.path.join(out, "coarse"), sd, ss, so, lambda k: np.zeros((sd[1], sd[0])))
rq = np.linalg.norm(Q - np.array([0.0, 0.0, 24.0]), axis=-1)
tumour = np.linalg.norm(Q - np.array([4.0, 2.0, 22.0]), axis=-1) < 5
liver = rq < 12
masks = np.stack([tumour, liver], -1)              # (x, y, z, segment)
pixel = np.transpose(masks, (2, 1, 0, 3)).astype(np.uint8)  # (slices, rows, cols, segments)
def desc(n, label, lab):
    return hd.seg.SegmentDescription(
        segment_number=n, segment_label=label,
        segmented_property_category=codes.SCT.Tissue, segmented_property_type=codes.SCT.Tissue,
        algorithm_type=hd.seg.SegmentAlgorithmTypeValues.MANUAL,
        display_color=hd.color.CIELabColor(*lab))
descs = [desc(1, "tumour", (53.24, 80.09, 67.20)), desc(2, "liver", (46.2, 20.0, 30.0))]
# fractional: 1 inside, 0.3 in a shell around the liver (below half: outside)
frac = pixel.astype(np.float32)
shell = np.transpose((rq >= 12) & (rq < 14), (2, 1, 0))
frac[..., 1][shell] = 0.3
for kind, data in [("BINARY", pixel), ("FRACTIONAL", frac)]:
    seg = hd.seg.Segmentation(
        source_images=src, pixel_array=data, segmentation_type=kind, segment_descriptions=descs,
        series_instance_uid=generate_uid(), series_number=10, sop_instance_uid=generate_uid(),
        instance_number=1, manufacturer="test", manufacturer_model_name="test",
        software_versions="1", device_serial_number="1")
    seg.save_as(os.path.join(out, f"seg-{kind.lower()}.dcm"))
# highdicom's own reading of the binary one, resampled into the CT's grid by position (nearest
# segmentation voxel to each CT voxel's centre).
seg = hd.seg.segread(os.path.join(out, "seg-binary.dcm"))
counts = {}
for n, label in [(1, "tumour"), (2, "liver")]:
    vol = seg.get_volume(segment_numbers=[n], combine_segments=False)
    # frames only where the segment is; get_volume places them on its own grid
    arr = vol.array[..., 0] if vol.array.ndim == 4 else vol.array
    aff = vol.affine  # voxel (i, j, k) of arr -> LPS
    ijk = np.rint((np.concatenate([P, np.ones(cd + (1,))], -1) @ np.linalg.inv(aff).T)[..., :3]).astype(int)
    inside = np.all((ijk >= 0) & (ijk < np.array(arr.shape)), -1)
    nn = np.where(inside[..., None], ijk, 0)
    hit = inside & (arr[nn[..., 0], nn[..., 1], nn[..., 2]] > 0)
    counts[label] = hit
# the smaller segment wins where they overlap (cao-xr's rule; the first of equal ones)
tum, liv = counts["tumour"], counts["liver"]
if tum.sum() <= liv.sum():
    liv = liv & ~tum
else:
    tum = tum & ~liv
# flat CT voxel indices (x fastest) of each
flat = lambda m: [int(i) for i in np.flatnonzero(np.transpose(m, (2, 1, 0)))]
print(json.dumps({"tumour": flat(tum), "liver": flat(liv)}))
