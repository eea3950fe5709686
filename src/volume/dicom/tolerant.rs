//! A tolerant first pass over a DICOM file: reads its element structure the way dcmtk does and
//! writes a clean copy ("DICM", file meta group, data set) that dicom-object reads. Scanners
//! write files that dicom-rs alone refuses or misreads:
//!
//! - no preamble and no "DICM" (ACR-NEMA style): a data set from byte 0 whose encoding
//!   (implicit or explicit VR little endian) is guessed from its first element, as dcmtk does;
//! - a file meta group read while the group is 0002, whatever its group length says;
//! - a non-standard VR in explicit-VR data: two upper-case letters are a VR from a later
//!   edition, with a 4-byte length; anything else (e.g. two zero bytes) has a 2-byte length
//!   (dcmtk's rule). The element is written with the dictionary's VR, or as UN;
//! - group lengths (gggg,0000) and command elements (group 0000) in a data set: dropped;
//! - a binary value whose length is no multiple of its value size (odd lengths): the whole
//!   values are kept, the rest is dropped (dcmtk reads it so);
//! - an undefined-length UN element holds implicit VR little endian (CP-246): it is written as a
//!   sequence in the file's own explicit VR;
//! - nothing after the top-level pixel data is read: trailing padding or garbage is ignored.
//!
//! Sequences and items are written with undefined length, so a fixed element never leaves an
//! enclosing length wrong. An element that declares more bytes than the file still holds is
//! refused before anything is allocated for it (dicom-rs would allocate, and zero, up to 4 GiB).

use crate::volume::VolumeError;
use dicom_core::dictionary::{DataDictionary, VirtualVr};
use dicom_core::{Tag, VR};
use dicom_dictionary_std::StandardDataDictionary;
use std::io::{BufReader, Read};
use std::path::Path;

const IMPLICIT_LE_UID: &str = "1.2.840.10008.1.2";
const EXPLICIT_LE_UID: &str = "1.2.840.10008.1.2.1";
const EXPLICIT_BE_UID: &str = "1.2.840.10008.1.2.2";
const DEFLATED_UID: &str = "1.2.840.10008.1.2.1.99";
const UNDEFINED: u32 = u32::MAX;
const PIXEL_DATA: (u16, u16) = (0x7FE0, 0x0010);
const ITEM: (u16, u16) = (0xFFFE, 0xE000);
const ITEM_END: (u16, u16) = (0xFFFE, 0xE00D);
const SEQUENCE_END: (u16, u16) = (0xFFFE, 0xE0DD);
/// Sequences nested deeper than this are refused (a hostile file must not exhaust the stack).
const MAX_NESTING: usize = 64;

/// How a data set is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Enc {
    little: bool,
    explicit: bool,
}

const IMPLICIT_LE: Enc = Enc {
    little: true,
    explicit: false,
};
const EXPLICIT_LE: Enc = Enc {
    little: true,
    explicit: true,
};

/// Where a DICOM file's content starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Start {
    /// Part 10: a file meta group after the 128-byte preamble and "DICM".
    Part10,
    /// A file meta group at byte 0 (no preamble, no "DICM").
    BareMeta,
    /// ACR-NEMA style: a data set at byte 0, no file meta group.
    BareDataSet,
}

/// Is `path` a DICOM file, and where does its content start? `None` for anything else (text,
/// images, archives): neither "DICM" at byte 128 nor a file meta or identifying (group 0008)
/// element at byte 0.
pub(super) fn sniff(path: &Path) -> Option<Start> {
    let mut head = Vec::with_capacity(132);
    std::fs::File::open(path)
        .ok()?
        .take(132)
        .read_to_end(&mut head)
        .ok()?;
    if head.get(128..132) == Some(b"DICM") {
        return Some(Start::Part10);
    }
    let h = head.get(..8)?;
    let group = u16::from_le_bytes([h[0], h[1]]);
    let element = u16::from_le_bytes([h[2], h[3]]);
    // the meta group starts with its group length, or (0002,0001) in writers that omit it
    if group == 0x0002 && element <= 0x0001 && VR::from_binary([h[4], h[5]]).is_some() {
        return Some(Start::BareMeta);
    }
    // an ACR-NEMA data set opens with group 0008 (identifying); its first length must fit
    let len = guess_encoding(h).map(|enc| {
        if enc.explicit {
            u16::from_le_bytes([h[6], h[7]]) as u64
        } else {
            u32::from_le_bytes([h[4], h[5], h[6], h[7]]) as u64
        }
    })?;
    let size = std::fs::metadata(path).ok()?.len();
    (group == 0x0008 && len <= size).then_some(Start::BareDataSet)
}

/// The encoding of a data set without a transfer syntax, from its first element header: a
/// standard VR after the tag means explicit VR little endian, anything else implicit.
fn guess_encoding(h: &[u8]) -> Option<Enc> {
    let vr = VR::from_binary([*h.get(4)?, *h.get(5)?]);
    Some(if vr.is_some() {
        EXPLICIT_LE
    } else {
        IMPLICIT_LE
    })
}

/// VRs written with a 2-reserved-byte, 4-byte length in explicit VR.
fn long_form(vr: VR) -> bool {
    use VR::*;
    matches!(
        vr,
        OB | OD | OF | OL | OV | OW | SQ | SV | UC | UN | UR | UT | UV
    )
}

/// Bytes per value of a binary VR (a value length must be a multiple of it).
fn value_size(vr: VR) -> u32 {
    use VR::*;
    match vr {
        US | SS | OW => 2,
        UL | SL | FL | OF | OL | AT => 4,
        FD | OD | SV | UV | OV => 8,
        _ => 1,
    }
}

/// The dictionary's VR for a tag, where it names exactly one.
fn dictionary_vr(group: u16, element: u16) -> Option<VR> {
    match StandardDataDictionary.by_tag(Tag(group, element))?.vr {
        VirtualVr::Exact(vr) => Some(vr),
        _ => None,
    }
}

/// One element header as read.
#[derive(Clone, Copy, Debug)]
struct Head {
    group: u16,
    element: u16,
    /// The VR as written in explicit VR, when it is a standard one.
    vr: Option<VR>,
    len: u32,
}

impl Head {
    fn tag(&self) -> (u16, u16) {
        (self.group, self.element)
    }
    /// The VR the element is written with: its own, else the dictionary's, else UN. A
    /// defined-length UN in little endian takes the dictionary's VR too, as pydicom reads it
    /// (a standard element written as UN by a writer that did not know it).
    fn vr(&self, enc: Enc) -> VR {
        let own = self
            .vr
            .filter(|&v| !(v == VR::UN && enc.little && self.len != UNDEFINED));
        own.or_else(|| dictionary_vr(self.group, self.element))
            .or(self.vr)
            .unwrap_or(VR::UN)
    }
}

struct Src<'p> {
    r: BufReader<std::fs::File>,
    pos: u64,
    size: u64,
    path: &'p Path,
}

impl Src<'_> {
    fn left(&self) -> u64 {
        self.size - self.pos
    }
    fn io(&self, e: std::io::Error) -> VolumeError {
        VolumeError::io(self.path, e)
    }
    fn bytes<const N: usize>(&mut self) -> Result<Option<[u8; N]>, VolumeError> {
        if self.left() < N as u64 {
            return Ok(None);
        }
        let mut b = [0u8; N];
        self.r.read_exact(&mut b).map_err(|e| self.io(e))?;
        self.pos += N as u64;
        Ok(Some(b))
    }
    fn back(&mut self, n: u64) -> Result<(), VolumeError> {
        self.r.seek_relative(-(n as i64)).map_err(|e| self.io(e))?;
        self.pos -= n;
        Ok(())
    }
    fn skip(&mut self, n: u64) -> Result<(), VolumeError> {
        self.r.seek_relative(n as i64).map_err(|e| self.io(e))?;
        self.pos += n;
        Ok(())
    }
    /// Appends the next `n` bytes (already checked to be in the file) to `out`.
    fn copy(&mut self, n: u64, out: &mut Vec<u8>) -> Result<(), VolumeError> {
        let at = out.len();
        out.resize(at + n as usize, 0);
        self.r.read_exact(&mut out[at..]).map_err(|e| self.io(e))?;
        self.pos += n;
        Ok(())
    }
    /// Refuses a length the rest of the file cannot hold.
    fn check(&self, h: &Head) -> Result<(), VolumeError> {
        if h.len != UNDEFINED && h.len as u64 > self.left() {
            return Err(VolumeError::format(
                self.path,
                format!(
                    "element ({:04X},{:04X}) declares {} bytes but the file holds only {} more \
                     (truncated, or a header that lies about a length)",
                    h.group,
                    h.element,
                    h.len,
                    self.left()
                ),
            ));
        }
        Ok(())
    }
    /// The next element header; `None` where fewer bytes are left than a header takes.
    fn head(&mut self, enc: Enc) -> Result<Option<Head>, VolumeError> {
        let Some(h) = self.bytes::<8>()? else {
            return Ok(None);
        };
        let u16_of = |b: [u8; 2]| {
            if enc.little {
                u16::from_le_bytes(b)
            } else {
                u16::from_be_bytes(b)
            }
        };
        let u32_of = |b: [u8; 4]| {
            if enc.little {
                u32::from_le_bytes(b)
            } else {
                u32::from_be_bytes(b)
            }
        };
        let (group, element) = (u16_of([h[0], h[1]]), u16_of([h[2], h[3]]));
        let mut head = Head {
            group,
            element,
            vr: None,
            len: u32_of([h[4], h[5], h[6], h[7]]),
        };
        // items and delimiters have no VR, implicit VR elements neither
        if group == 0xFFFE || !enc.explicit {
            return Ok(Some(head));
        }
        let raw = [h[4], h[5]];
        head.vr = VR::from_binary(raw);
        let long = match head.vr {
            Some(vr) => long_form(vr),
            // dcmtk: upper-case letters are a later edition's VR (4-byte length), anything
            // else is an illegal VR with a 2-byte length
            None => raw.iter().all(u8::is_ascii_uppercase),
        };
        if !long {
            head.len = u16_of([h[6], h[7]]) as u32;
            return Ok(Some(head));
        }
        let Some(l) = self.bytes::<4>()? else {
            return Ok(None);
        };
        head.len = u32_of(l);
        Ok(Some(head))
    }
}

struct Out {
    buf: Vec<u8>,
    enc: Enc,
}

impl Out {
    fn u16(&mut self, v: u16) {
        let b = if self.enc.little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        };
        self.buf.extend_from_slice(&b);
    }
    fn u32(&mut self, v: u32) {
        let b = if self.enc.little {
            v.to_le_bytes()
        } else {
            v.to_be_bytes()
        };
        self.buf.extend_from_slice(&b);
    }
    fn tag(&mut self, (group, element): (u16, u16)) {
        self.u16(group);
        self.u16(element);
    }
    /// An item or delimiter header.
    fn item(&mut self, tag: (u16, u16), len: u32) {
        self.tag(tag);
        self.u32(len);
    }
    /// An element header; a VR that cannot hold `len` in its short form becomes UN.
    fn element(&mut self, tag: (u16, u16), vr: VR, len: u32) {
        self.tag(tag);
        if !self.enc.explicit {
            self.u32(len);
            return;
        }
        let vr = if !long_form(vr) && len > u16::MAX as u32 {
            VR::UN
        } else {
            vr
        };
        self.buf.extend_from_slice(&vr.to_bytes());
        if long_form(vr) {
            self.u16(0);
            self.u32(len);
        } else {
            self.u16(len as u16);
        }
    }
}

/// How far a data set is read.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum Until {
    /// Everything before the top-level pixel data (whose length is still checked).
    PixelData,
    /// Everything up to the end of the top-level pixel data.
    End,
}

/// Where a list of elements ends.
#[derive(Clone, Copy)]
enum Ends {
    /// The top-level data set: at the end of the file, or its pixel data.
    TopLevel,
    /// A defined-length item: at this file position.
    At(u64),
    /// An undefined-length item: at its item delimiter.
    Delimiter,
}

struct Walk<'p> {
    src: Src<'p>,
    out: Out,
    until: Until,
}

impl Walk<'_> {
    fn fail(&self, msg: String) -> VolumeError {
        VolumeError::format(self.src.path, msg)
    }

    /// Copies the elements of a data set or item encoded as `enc`.
    fn elements(&mut self, enc: Enc, ends: Ends, depth: usize) -> Result<(), VolumeError> {
        if depth > MAX_NESTING {
            return Err(self.fail(format!(
                "sequences nested more than {MAX_NESTING} deep (a corrupt file?)"
            )));
        }
        loop {
            if let Ends::At(end) = ends {
                if self.src.pos >= end {
                    return Ok(());
                }
            }
            let Some(h) = self.src.head(enc)? else {
                return match ends {
                    // a few stray bytes after the last element
                    Ends::TopLevel => Ok(()),
                    _ => Err(self.fail("the file ends inside a sequence (truncated)".into())),
                };
            };
            match h.tag() {
                ITEM_END if matches!(ends, Ends::Delimiter) => return Ok(()),
                // stray delimiters (dicom-rs and dcmtk skip them too)
                ITEM_END | SEQUENCE_END => continue,
                ITEM => {
                    return Err(self.fail(format!(
                        "an item where a data element is expected (at byte {})",
                        self.src.pos - 8
                    )))
                }
                _ => {}
            }
            self.src.check(&h)?;
            // group lengths and command elements: not needed, and lengths we may change
            if h.element == 0x0000 || h.group == 0x0000 {
                if h.len == UNDEFINED {
                    return Err(self.fail(format!(
                        "group length ({:04X},0000) with an undefined length",
                        h.group
                    )));
                }
                self.src.skip(h.len as u64)?;
                continue;
            }
            let top = matches!(ends, Ends::TopLevel);
            if h.tag() == PIXEL_DATA {
                if top && self.until == Until::PixelData {
                    return Ok(());
                }
                if h.len == UNDEFINED {
                    self.fragments(enc)?;
                } else {
                    self.primitive(&h, h.vr(enc))?;
                }
                if top {
                    // anything after it is padding or garbage to dcmtk and pydicom alike
                    return Ok(());
                }
                continue;
            }
            let vr = h.vr(enc);
            if h.len == UNDEFINED || vr == VR::SQ {
                // a sequence in a UN (or unknown VR) element of explicit VR data is encoded in
                // implicit VR little endian (CP-246)
                let inner = if enc.explicit && h.vr != Some(VR::SQ) {
                    IMPLICIT_LE
                } else {
                    enc
                };
                if inner != enc && !self.out.enc.little {
                    return Err(VolumeError::unsupported(
                        self.src.path,
                        format!(
                            "({:04X},{:04X}): an implicit-VR sequence inside big endian data",
                            h.group, h.element
                        ),
                    ));
                }
                self.out.element(h.tag(), VR::SQ, UNDEFINED);
                self.sequence(inner, h.len, depth + 1)?;
                self.out.item(SEQUENCE_END, 0);
                continue;
            }
            self.primitive(&h, vr)?;
        }
    }

    /// Copies one value; a binary one loses the bytes past its last whole value.
    fn primitive(&mut self, h: &Head, mut vr: VR) -> Result<(), VolumeError> {
        let mut keep = h.len;
        // dicom-rs reads an odd-length OW as 16-bit words and loses the stream position;
        // little-endian OW bytes are OB bytes
        if h.tag() == PIXEL_DATA && vr == VR::OW && h.len % 2 == 1 && self.out.enc.little {
            vr = VR::OB;
        }
        keep -= keep % value_size(vr);
        self.out.element(h.tag(), vr, keep);
        self.src.copy(keep as u64, &mut self.out.buf)?;
        self.src.skip((h.len - keep) as u64)
    }

    /// Copies the items of a sequence (its header is written) and ends it.
    fn sequence(&mut self, enc: Enc, len: u32, depth: usize) -> Result<(), VolumeError> {
        let end = (len != UNDEFINED).then(|| self.src.pos + len as u64);
        loop {
            if end.is_some_and(|e| self.src.pos >= e) {
                return Ok(());
            }
            let Some(h) = self.src.head(enc)? else {
                return Err(self.fail("the file ends inside a sequence (truncated)".into()));
            };
            match h.tag() {
                SEQUENCE_END if end.is_none() => return Ok(()),
                SEQUENCE_END | ITEM_END => continue,
                ITEM => {
                    self.src.check(&h)?;
                    self.out.item(ITEM, UNDEFINED);
                    let ends = if h.len == UNDEFINED {
                        Ends::Delimiter
                    } else {
                        Ends::At(self.src.pos + h.len as u64)
                    };
                    self.elements(enc, ends, depth)?;
                    self.out.item(ITEM_END, 0);
                }
                (g, e) => {
                    return Err(self.fail(format!(
                        "a sequence holds ({g:04X},{e:04X}) where an item is expected"
                    )))
                }
            }
        }
    }

    /// Copies encapsulated pixel data: its fragments up to the sequence delimiter.
    fn fragments(&mut self, enc: Enc) -> Result<(), VolumeError> {
        self.out.element(PIXEL_DATA, VR::OB, UNDEFINED);
        loop {
            let Some(h) = self.src.head(enc)? else {
                return Err(self
                    .fail("the file ends inside the encapsulated pixel data (truncated)".into()));
            };
            match h.tag() {
                SEQUENCE_END => {
                    self.out.item(SEQUENCE_END, 0);
                    return Ok(());
                }
                ITEM if h.len != UNDEFINED => {
                    self.src.check(&h)?;
                    self.out.item(ITEM, h.len);
                    self.src.copy(h.len as u64, &mut self.out.buf)?;
                }
                (g, e) => {
                    return Err(self.fail(format!(
                        "the encapsulated pixel data holds ({g:04X},{e:04X}) where a fragment \
                         is expected"
                    )))
                }
            }
        }
    }
}

/// What the file meta group says.
#[derive(Default)]
struct Meta {
    sop_class: Option<String>,
    sop_instance: Option<String>,
    transfer_syntax: Option<String>,
}

fn text(v: &[u8]) -> String {
    String::from_utf8_lossy(v)
        .trim_end_matches(['\0', ' '])
        .trim_start()
        .to_string()
}

/// Reads the meta group's elements (explicit VR little endian) while their group is 0002.
fn read_meta(src: &mut Src) -> Result<Meta, VolumeError> {
    let mut meta = Meta::default();
    loop {
        let at = src.pos;
        let Some(h) = src.head(EXPLICIT_LE)? else {
            return Ok(meta);
        };
        if h.group != 0x0002 {
            src.back(src.pos - at)?;
            return Ok(meta);
        }
        if h.len == UNDEFINED {
            return Err(VolumeError::format(
                src.path,
                format!(
                    "file meta element (0002,{:04X}) has an undefined length",
                    h.element
                ),
            ));
        }
        src.check(&h)?;
        let slot = match h.element {
            0x0002 => &mut meta.sop_class,
            0x0003 => &mut meta.sop_instance,
            0x0010 => &mut meta.transfer_syntax,
            _ => {
                src.skip(h.len as u64)?;
                continue;
            }
        };
        let mut v = Vec::new();
        src.copy(h.len as u64, &mut v)?;
        *slot = Some(text(&v));
    }
}

/// The file meta group as dicom-object reads it: group length, version, the UIDs.
fn write_meta(meta: &Meta, ts: &str) -> Vec<u8> {
    let mut body = Out {
        buf: Vec::new(),
        enc: EXPLICIT_LE,
    };
    body.element((0x0002, 0x0001), VR::OB, 2);
    body.buf.extend_from_slice(&[0, 1]);
    for (element, v) in [
        (0x0002, meta.sop_class.as_deref()),
        (0x0003, meta.sop_instance.as_deref()),
        (0x0010, Some(ts)),
    ] {
        if let Some(v) = v.filter(|v| !v.is_empty()) {
            let mut b = v.as_bytes().to_vec();
            if b.len() % 2 == 1 {
                b.push(0);
            }
            body.element((0x0002, element), VR::UI, b.len() as u32);
            body.buf.extend_from_slice(&b);
        }
    }
    let mut out = Out {
        buf: b"DICM".to_vec(),
        enc: EXPLICIT_LE,
    };
    out.element((0x0002, 0x0000), VR::UL, 4);
    out.u32(body.buf.len() as u32);
    out.buf.extend_from_slice(&body.buf);
    out.buf
}

/// The file rewritten as "DICM", a clean file meta group and the data set read `until`, for
/// dicom-object's `from_reader` without a preamble.
pub(super) fn read(path: &Path, start: Start, until: Until) -> Result<Vec<u8>, VolumeError> {
    let io = |e: std::io::Error| VolumeError::io(path, e);
    let file = std::fs::File::open(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    let mut src = Src {
        r: BufReader::new(file),
        pos: 0,
        size,
        path,
    };
    let meta = match start {
        Start::Part10 => {
            src.skip(132)?;
            read_meta(&mut src)?
        }
        Start::BareMeta => read_meta(&mut src)?,
        Start::BareDataSet => Meta::default(),
    };
    let declared = meta.transfer_syntax.clone().unwrap_or_default();
    let enc = match declared.as_str() {
        "" => {
            // no transfer syntax: guessed from the first element, as for ACR-NEMA files
            let at = src.pos;
            let first = src.bytes::<8>()?;
            src.back(src.pos - at)?;
            first
                .and_then(|h| guess_encoding(&h))
                .unwrap_or(IMPLICIT_LE)
        }
        IMPLICIT_LE_UID => IMPLICIT_LE,
        EXPLICIT_BE_UID => Enc {
            little: false,
            explicit: true,
        },
        _ => EXPLICIT_LE,
    };
    let ts = match (declared.as_str(), enc.explicit) {
        ("", true) => EXPLICIT_LE_UID,
        ("", false) => IMPLICIT_LE_UID,
        (d, _) => d,
    };
    let mut bytes = write_meta(&meta, ts);
    if ts == DEFLATED_UID {
        // a deflated data set cannot be walked; dicom-rs inflates and reads it
        let left = src.left();
        src.copy(left, &mut bytes)?;
        return Ok(bytes);
    }
    let mut walk = Walk {
        src,
        out: Out { buf: bytes, enc },
        until,
    };
    walk.elements(enc, Ends::TopLevel, 0)?;
    Ok(walk.out.buf)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::test_scratch::Scratch;

    /// An explicit VR little endian Part 10 file around `data_set`.
    fn part10(data_set: &[u8]) -> Vec<u8> {
        let meta = Meta::default();
        let mut b = vec![0u8; 128];
        b.extend_from_slice(&write_meta(&meta, EXPLICIT_LE_UID));
        b.extend_from_slice(data_set);
        b
    }

    fn read_bytes(name: &str, bytes: &[u8]) -> Result<Vec<u8>, String> {
        let s = Scratch::new("tolerant");
        let p = s.0.join(name);
        std::fs::write(&p, bytes).unwrap();
        let start = sniff(&p).ok_or("not DICOM")?;
        read(&p, start, Until::End).map_err(|e| e.to_string())
    }

    #[test]
    fn deep_nesting_is_refused_without_exhausting_the_stack() {
        // 100 000 nested undefined-length sequences and items, never closed
        let mut ds = Vec::new();
        for _ in 0..100_000 {
            ds.extend_from_slice(b"\x08\x00\x15\x11SQ\0\0\xff\xff\xff\xff");
            ds.extend_from_slice(b"\xfe\xff\x00\xe0\xff\xff\xff\xff");
        }
        let e = read_bytes("deep.dcm", &part10(&ds)).unwrap_err();
        assert!(
            e.contains("deep.dcm") && e.contains("nested more than 64"),
            "{e}"
        );
    }

    #[test]
    fn lengths_past_the_end_and_stray_structure_are_refused_by_name() {
        let cases: [(&[u8], &str); 4] = [
            (b"\x10\x00\x10\x00PN\x10\x00abc", "declares 16 bytes"),
            (
                b"\x08\x00\x15\x11SQ\0\0\xff\xff\xff\xff",
                "ends inside a sequence",
            ),
            (
                b"\xfe\xff\x00\xe0\x00\x00\x00\x00",
                "an item where a data element",
            ),
            (
                b"\xe0\x7f\x10\x00OB\0\0\xff\xff\xff\xff\x10\x00\x10\x00PN\x00\x00",
                "where a fragment is expected",
            ),
        ];
        for (ds, want) in cases {
            let e = read_bytes("x.dcm", &part10(ds)).unwrap_err();
            assert!(e.contains("x.dcm") && e.contains(want), "{e}");
        }
    }

    #[test]
    fn a_non_standard_vr_has_the_length_field_dcmtk_reads() {
        // (0028,0010) Rows with two zero bytes as VR: a 2-byte length; (0008,103E) with "ZZ":
        // a 4-byte length; both written with the dictionary's VR
        let ds = b"\x08\x00\x3e\x10ZZ\0\0\x04\x00\x00\x00abcd\x28\x00\x10\x00\0\0\x02\x00\x05\x00";
        let out = read_bytes("vr.dcm", &part10(ds)).unwrap();
        let tail = &out[out.len() - 22..];
        assert_eq!(
            tail,
            b"\x08\x00\x3e\x10LO\x04\x00abcd\x28\x00\x10\x00US\x02\x00\x05\x00"
        );
    }

    #[test]
    fn files_that_are_not_dicom_are_not_taken_for_acr_nema() {
        let s = Scratch::new("sniff");
        for (name, bytes) in [
            ("text", b"not a DICOM file\n".to_vec()),
            ("empty", Vec::new()),
            ("short", b"\x08\x00".to_vec()),
            // group 0008, but a first length far past the end of the file
            ("long", b"\x08\x00\x05\x00\xff\xff\xff\x7f".to_vec()),
        ] {
            let p = s.0.join(name);
            std::fs::write(&p, bytes).unwrap();
            assert_eq!(sniff(&p), None, "{name}");
        }
        let p = s.0.join("acr");
        std::fs::write(&p, b"\x08\x00\x60\x00\x02\x00\x00\x00CT").unwrap();
        assert_eq!(sniff(&p), Some(Start::BareDataSet));
    }
}
