//! The real CT head: InVesalius' "Cranium" example (Debian package `invesalius-examples`),
//! converted once into a gzip NRRD in the user's cache directory.
//!
//! Orientation (checked by rendering the converted volume into PNGs, window -1000..2000 HU:
//! axial slices with row = j, column = i; sagittal and coronal mid-slices and MIPs with row 0
//! = largest k): the matrix holds 108 axial slices of 256 x 256. The lowest slices (k = 0) cut
//! through the maxilla and the upper teeth, the top slices through the cranial vault, so +k
//! runs inferior -> superior. In the axial slices the nose, maxilla, teeth and frontal sinus
//! lie at LARGE j (bottom of the image) and the occiput plus the curved head rest of the table
//! at small j; the sagittal pictures show the face at large j as well. So +j runs posterior ->
//! anterior, the opposite of DICOM's row order. This matches InVesalius' DICOM import, which
//! flips each slice vertically (`read_dcm_slice_as_np2(f)[::-1]`) and leaves the columns
//! alone. Left/right cannot be told from the (symmetric) anatomy, and there is no marker in the
//! images; since the columns are kept in DICOM order (column 0 = patient right for an axial
//! series), +i runs right -> left. Hence `directions` has the columns +i = (1,0,0) (left),
//! +j = (0,-1,0) (anterior), +k = (0,0,1) (superior); note its determinant is -1.

use super::{nrrd, Modality, Volume, VolumeError};
use glam::{DMat3, DVec3};
use std::ffi::OsStr;
use std::fs;
use std::path::{Path, PathBuf};
use std::process::Command;

/// LPS unit vectors of the stored i, j, k axes (see the module comment).
pub const CT_HEAD_DIRECTIONS: DMat3 = DMat3::from_cols(
    DVec3::new(1.0, 0.0, 0.0),
    DVec3::new(0.0, -1.0, 0.0),
    DVec3::new(0.0, 0.0, 1.0),
);

/// Debian package holding `Cranium.inv3`.
const PACKAGE: &str = "invesalius-examples";
/// Location of the example inside the package.
const INV3_IN_PACKAGE: &str = "usr/share/doc/invesalius-examples/examples/Cranium.inv3";

/// Where fetched data are cached: `$CAO_XR_DATA`, else `$XDG_CACHE_HOME/cao-xr`, else
/// `$HOME/.cache/cao-xr` (else a `cao-xr` folder in the temporary directory).
pub fn cache_dir() -> PathBuf {
    let var = |name: &str| {
        std::env::var_os(name)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    if let Some(dir) = var("CAO_XR_DATA") {
        return dir;
    }
    if let Some(dir) = var("XDG_CACHE_HOME").filter(|d| d.is_absolute()) {
        return dir.join("cao-xr");
    }
    if let Some(home) = var("HOME") {
        return home.join(".cache").join("cao-xr");
    }
    std::env::temp_dir().join("cao-xr")
}

/// `cache_dir()/ct-head.nrrd`.
pub fn cached_path() -> PathBuf {
    cache_dir().join("ct-head.nrrd")
}

/// Removes the scratch directory however `fetch` ends.
struct TempDir(PathBuf);

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = fs::remove_dir_all(&self.0);
    }
}

/// Runs a tool; on failure returns a line naming the command with its stderr.
fn run(cmd: &mut Command) -> Result<(), String> {
    let shown = format!("{:?}", cmd);
    match cmd.output() {
        Err(e) => Err(format!("could not run {shown}: {e}")),
        Ok(out) if out.status.success() => Ok(()),
        Ok(out) => {
            let stderr = String::from_utf8_lossy(&out.stderr);
            let stderr = stderr.trim();
            let stderr = if stderr.is_empty() {
                "(no output)"
            } else {
                stderr
            };
            Err(format!("{shown} failed ({}): {stderr}", out.status))
        }
    }
}

/// Finds a file called `name` under `dir` (at most `depth` levels down).
fn find_file(dir: &Path, name: &str, depth: usize) -> Option<PathBuf> {
    let mut entries: Vec<_> = fs::read_dir(dir).ok()?.filter_map(|e| e.ok()).collect();
    entries.sort_by_key(|e| e.file_name());
    for e in &entries {
        let p = e.path();
        if p.is_file() && e.file_name() == OsStr::new(name) {
            return Some(p);
        }
    }
    if depth > 0 {
        for e in &entries {
            let p = e.path();
            if p.is_dir() {
                if let Some(found) = find_file(&p, name, depth - 1) {
                    return Some(found);
                }
            }
        }
    }
    None
}

/// Removes the working folders (`.fetch-PID-STAMP`) of fetches whose process is gone (killed or
/// interrupted: their own clean-up never ran). Only where /proc tells which processes live.
fn remove_abandoned_fetches(cache: &Path) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = fs::read_dir(cache) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let pid = name
            .to_str()
            .and_then(|n| n.strip_prefix(".fetch-"))
            .and_then(|rest| rest.split('-').next())
            .and_then(|pid| pid.parse::<u32>().ok());
        if let Some(pid) = pid {
            if !Path::new(&format!("/proc/{pid}")).exists() {
                let _ = fs::remove_dir_all(e.path());
            }
        }
    }
}

/// Downloads the Debian package `invesalius-examples` with `apt-get download`, extracts the
/// Cranium CT, converts it and writes it (gzip NRRD) to [`cached_path`]. Returns that path.
/// `progress` receives one short line per step.
pub fn fetch(progress: &mut dyn FnMut(&str)) -> Result<PathBuf, VolumeError> {
    let dest = cached_path();
    let cache = cache_dir();
    fs::create_dir_all(&cache).map_err(|e| VolumeError::io(&cache, e))?;
    remove_abandoned_fetches(&cache);
    let stamp = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos())
        .unwrap_or(0);
    let tmp = TempDir(cache.join(format!(".fetch-{}-{}", std::process::id(), stamp)));
    fs::create_dir_all(&tmp.0).map_err(|e| VolumeError::io(&tmp.0, e))?;
    let fail = |msg: String| VolumeError::format(&dest, msg);

    progress(&format!(
        "downloading the Debian package {PACKAGE} with apt-get"
    ));
    let download = || {
        run(Command::new("apt-get")
            .arg("download")
            .arg(PACKAGE)
            .current_dir(&tmp.0))
    };
    if let Err(first) = download() {
        progress(&format!(
            "apt-get download failed; running apt-get update ({first})"
        ));
        let update = run(Command::new("apt-get").arg("update"));
        if let Err(second) = download() {
            let update = update.err().map(|e| format!("; {e}")).unwrap_or_default();
            return Err(fail(format!(
                "could not download the Debian package {PACKAGE}: {second}{update}. Run this \
                 as root on Debian (or a derivative) whose apt sources reach a Debian mirror, \
                 or place a CT volume at this path yourself"
            )));
        }
    }
    let deb = fs::read_dir(&tmp.0)
        .map_err(|e| VolumeError::io(&tmp.0, e))?
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .find(|p| p.extension() == Some(OsStr::new("deb")))
        .ok_or_else(|| {
            fail(format!(
                "apt-get download left no .deb file in {}",
                tmp.0.display()
            ))
        })?;

    progress(&format!("unpacking {}", deb.display()));
    let pkg_dir = tmp.0.join("pkg");
    run(Command::new("dpkg-deb").arg("-x").arg(&deb).arg(&pkg_dir)).map_err(fail)?;
    let inv3 = pkg_dir.join(INV3_IN_PACKAGE);
    if !inv3.is_file() {
        return Err(fail(format!(
            "{} does not contain {INV3_IN_PACKAGE}",
            deb.display()
        )));
    }

    progress("extracting Cranium.inv3");
    let inv_dir = tmp.0.join("inv3");
    fs::create_dir_all(&inv_dir).map_err(|e| VolumeError::io(&inv_dir, e))?;
    run(Command::new("tar")
        .arg("-xzf")
        .arg(&inv3)
        .arg("-C")
        .arg(&inv_dir))
    .map_err(fail)?;
    let plist = find_file(&inv_dir, "main.plist", 3)
        .ok_or_else(|| fail(format!("{} holds no main.plist", inv3.display())))?;
    let dir = plist.parent().unwrap_or(&inv_dir);

    progress("converting to NRRD");
    let vol = convert_inv3_dir(dir)?;
    nrrd::write_volume(&dest, &vol, true)?;
    drop(tmp);
    progress(&format!("wrote {}", dest.display()));
    Ok(dest)
}

/// Converts an extracted InVesalius project directory (`main.plist` + `matrix.dat`) into a
/// volume named "ct-head".
pub fn convert_inv3_dir(dir: &Path) -> Result<Volume, VolumeError> {
    let plist_path = dir.join("main.plist");
    let text = fs::read_to_string(&plist_path).map_err(|e| VolumeError::io(&plist_path, e))?;
    let root = plist::parse(&text).map_err(|m| VolumeError::format(&plist_path, m))?;
    let bad = |m: &str| VolumeError::format(&plist_path, m.to_string());

    let matrix = root.get("matrix").ok_or_else(|| bad("no `matrix` dict"))?;
    let dtype = matrix
        .get("dtype")
        .and_then(|v| v.as_str())
        .ok_or_else(|| bad("no matrix dtype"))?;
    if dtype != "int16" {
        return Err(VolumeError::unsupported(
            &plist_path,
            format!("matrix dtype {dtype:?} (only int16 is supported)"),
        ));
    }
    let shape: Vec<i64> = matrix
        .get("shape")
        .and_then(|v| v.as_array())
        .map(|a| a.iter().filter_map(|v| v.as_int()).collect())
        .unwrap_or_default();
    if shape.len() != 3 || shape.iter().any(|&s| s <= 0) {
        return Err(bad(
            "matrix shape must be three positive integers [z, y, x]",
        ));
    }
    let dims = [shape[2] as u64, shape[1] as u64, shape[0] as u64];
    let spacing: Vec<f64> = root
        .get("spacing")
        .and_then(|v| v.as_array())
        .map(|a| a.iter().filter_map(|v| v.as_f64()).collect())
        .unwrap_or_default();
    if spacing.len() != 3 || spacing.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(bad("spacing must be three positive numbers [x, y, z]"));
    }
    let modality = match root.get("modality").and_then(|v| v.as_str()) {
        Some(m) if m.eq_ignore_ascii_case("CT") => Modality::Ct,
        Some(m) if m.eq_ignore_ascii_case("MR") || m.eq_ignore_ascii_case("MRI") => Modality::Mr,
        _ => Modality::Unknown,
    };
    let file = matrix
        .get("filename")
        .and_then(|v| v.as_str())
        .unwrap_or("matrix.dat");
    // Only a plain file name inside `dir` is accepted.
    let file = Path::new(file)
        .file_name()
        .unwrap_or(OsStr::new("matrix.dat"));
    let data_path = dir.join(file);

    let (count, bytes) = super::checked_size(&data_path, dims, 2)?;
    let len = fs::metadata(&data_path)
        .map_err(|e| VolumeError::io(&data_path, e))?
        .len();
    if len != bytes {
        return Err(VolumeError::format(
            &data_path,
            format!(
                "expected {bytes} bytes ({} x {} x {} int16), found {len}",
                dims[0], dims[1], dims[2]
            ),
        ));
    }
    let file = fs::File::open(&data_path).map_err(|e| VolumeError::io(&data_path, e))?;
    let (voxels, got) = super::read_samples(
        &mut std::io::BufReader::new(file),
        super::SampleFormat::I16,
        count,
        false,
        true,
    )
    .map_err(|e| VolumeError::io(&data_path, e))?;
    if got != bytes {
        return Err(VolumeError::format(
            &data_path,
            format!("file shrank while reading: expected {bytes} bytes, read {got}"),
        ));
    }
    Ok(Volume {
        whole_range: None,
        name: "ct-head".into(),
        dims: [dims[0] as usize, dims[1] as usize, dims[2] as usize],
        spacing: [spacing[0], spacing[1], spacing[2]],
        // See the module comment: +i = patient left, +j = anterior, +k = superior.
        directions: CT_HEAD_DIRECTIONS,
        origin: DVec3::ZERO,
        modality,
        voxels,
        labels: None,
    })
}

/// Just enough of Apple's XML property lists for InVesalius' `main.plist`.
mod plist {
    #[derive(Debug, Clone, PartialEq)]
    pub enum Value {
        Dict(Vec<(String, Value)>),
        Array(Vec<Value>),
        Str(String),
        Int(i64),
        Real(f64),
        Bool(bool),
        Other,
    }

    impl Value {
        pub fn get(&self, key: &str) -> Option<&Value> {
            match self {
                Value::Dict(items) => items.iter().find(|(k, _)| k == key).map(|(_, v)| v),
                _ => None,
            }
        }
        pub fn as_str(&self) -> Option<&str> {
            match self {
                Value::Str(s) => Some(s),
                _ => None,
            }
        }
        pub fn as_array(&self) -> Option<&[Value]> {
            match self {
                Value::Array(a) => Some(a),
                _ => None,
            }
        }
        pub fn as_int(&self) -> Option<i64> {
            match self {
                Value::Int(i) => Some(*i),
                _ => None,
            }
        }
        pub fn as_f64(&self) -> Option<f64> {
            match self {
                Value::Real(r) => Some(*r),
                Value::Int(i) => Some(*i as f64),
                _ => None,
            }
        }
    }

    #[derive(Debug, PartialEq)]
    enum Token {
        Open(String),
        Close(String),
        Empty(String),
        Text(String),
    }

    fn unescape(s: &str) -> String {
        s.replace("&lt;", "<")
            .replace("&gt;", ">")
            .replace("&quot;", "\"")
            .replace("&apos;", "'")
            .replace("&amp;", "&")
    }

    fn tokenize(text: &str) -> Result<Vec<Token>, String> {
        let mut out = Vec::new();
        let mut rest = text;
        while !rest.is_empty() {
            if let Some(after) = rest.strip_prefix("<!--") {
                let end = after.find("-->").ok_or("unterminated comment")?;
                rest = &after[end + 3..];
            } else if let Some(after) = rest.strip_prefix('<') {
                let end = after.find('>').ok_or("unterminated tag")?;
                let tag = &after[..end];
                rest = &after[end + 1..];
                if tag.starts_with('?') || tag.starts_with('!') {
                    continue;
                }
                let name = |t: &str| t.split_whitespace().next().unwrap_or("").to_string();
                if let Some(t) = tag.strip_prefix('/') {
                    out.push(Token::Close(name(t)));
                } else if let Some(t) = tag.strip_suffix('/') {
                    out.push(Token::Empty(name(t)));
                } else {
                    out.push(Token::Open(name(tag)));
                }
            } else {
                let end = rest.find('<').unwrap_or(rest.len());
                let t = &rest[..end];
                if !t.trim().is_empty() {
                    out.push(Token::Text(unescape(t)));
                }
                rest = &rest[end..];
            }
        }
        Ok(out)
    }

    struct Parser {
        tokens: Vec<Token>,
        pos: usize,
    }

    impl Parser {
        fn next(&mut self) -> Option<&Token> {
            let t = self.tokens.get(self.pos);
            self.pos += 1;
            t
        }
        fn peek(&self) -> Option<&Token> {
            self.tokens.get(self.pos)
        }
        /// Text up to the closing tag `name` (empty when there is none).
        fn text_until(&mut self, name: &str) -> Result<String, String> {
            let mut s = String::new();
            loop {
                match self.next() {
                    Some(Token::Text(t)) => s.push_str(t),
                    Some(Token::Close(n)) if n == name => return Ok(s),
                    other => return Err(format!("unexpected {other:?} inside <{name}>")),
                }
            }
        }
        fn value(&mut self, depth: usize) -> Result<Value, String> {
            if depth > 64 {
                return Err("nesting too deep".into());
            }
            let tok = match self.next() {
                Some(Token::Open(n)) => n.clone(),
                Some(Token::Empty(n)) => {
                    return Ok(match n.as_str() {
                        "true" => Value::Bool(true),
                        "false" => Value::Bool(false),
                        "dict" => Value::Dict(Vec::new()),
                        "array" => Value::Array(Vec::new()),
                        "string" => Value::Str(String::new()),
                        _ => Value::Other,
                    })
                }
                other => return Err(format!("expected a value, found {other:?}")),
            };
            match tok.as_str() {
                "dict" => {
                    let mut items = Vec::new();
                    loop {
                        match self.next() {
                            Some(Token::Close(n)) if n == "dict" => return Ok(Value::Dict(items)),
                            Some(Token::Open(n)) if n == "key" => {
                                let key = self.text_until("key")?.trim().to_string();
                                let v = self.value(depth + 1)?;
                                items.push((key, v));
                            }
                            other => return Err(format!("unexpected {other:?} in <dict>")),
                        }
                    }
                }
                "array" => {
                    let mut items = Vec::new();
                    loop {
                        if let Some(Token::Close(n)) = self.peek() {
                            if n == "array" {
                                self.pos += 1;
                                return Ok(Value::Array(items));
                            }
                        }
                        items.push(self.value(depth + 1)?);
                    }
                }
                "string" => Ok(Value::Str(self.text_until("string")?)),
                "integer" => {
                    let t = self.text_until("integer")?;
                    t.trim()
                        .parse()
                        .map(Value::Int)
                        .map_err(|_| format!("bad integer {t:?}"))
                }
                "real" => {
                    let t = self.text_until("real")?;
                    t.trim()
                        .parse()
                        .map(Value::Real)
                        .map_err(|_| format!("bad real {t:?}"))
                }
                other => {
                    // Skip unknown elements (date, data, ...) including nested content.
                    let mut level = 1;
                    while level > 0 {
                        match self.next() {
                            Some(Token::Open(_)) => level += 1,
                            Some(Token::Close(_)) => level -= 1,
                            Some(_) => {}
                            None => return Err(format!("unterminated <{other}>")),
                        }
                    }
                    Ok(Value::Other)
                }
            }
        }
    }

    /// Parses a property list and returns its top-level value (the `<plist>` wrapper removed).
    pub fn parse(text: &str) -> Result<Value, String> {
        let tokens = tokenize(text)?;
        let mut p = Parser { tokens, pos: 0 };
        if let Some(Token::Open(n)) = p.peek() {
            if n == "plist" {
                p.pos += 1;
            }
        }
        p.value(0).map_err(|e| format!("property list: {e}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const REFERENCE: &str = "/tmp/ct/inv/tmpocjcea";

    #[test]
    fn plist_parses() {
        let v = plist::parse(
            "<?xml version=\"1.0\"?><!DOCTYPE plist><plist version=\"1.0\"><dict>\
             <key>a</key><array><integer>1</integer><real>2.5</real></array>\
             <key>b</key><dict><key>c</key><string>x &amp; y</string><key>d</key><true/></dict>\
             <key>e</key><date>2012</date></dict></plist>",
        )
        .unwrap();
        let a = v.get("a").unwrap().as_array().unwrap();
        assert_eq!(a[0].as_int(), Some(1));
        assert_eq!(a[1].as_f64(), Some(2.5));
        assert_eq!(
            v.get("b").unwrap().get("c").unwrap().as_str(),
            Some("x & y")
        );
        assert_eq!(
            v.get("b").unwrap().get("d"),
            Some(&plist::Value::Bool(true))
        );
        assert_eq!(v.get("e"), Some(&plist::Value::Other));
        assert!(plist::parse("<plist><dict><key>a</key>").is_err());
    }

    #[test]
    fn abandoned_fetch_folders_go_and_live_ones_stay() {
        let cache = std::env::temp_dir().join(format!("cao-fetches-{}", std::process::id()));
        // A PID above the kernel's pid_max limit (4194304) names no process.
        let dead = cache.join(".fetch-4194305-1");
        let live = cache.join(format!(".fetch-{}-2", std::process::id()));
        let other = cache.join("ct-head.nrrd.d");
        for d in [&dead, &live, &other] {
            fs::create_dir_all(d.join("pkg")).unwrap();
        }
        remove_abandoned_fetches(&cache);
        assert!(!dead.exists(), "a dead fetch's folder stayed");
        assert!(live.exists() && other.exists());
        fs::remove_dir_all(&cache).unwrap();
    }

    #[test]
    fn cache_paths() {
        assert!(cached_path().ends_with("ct-head.nrrd"));
        assert_eq!(cached_path().parent(), Some(cache_dir().as_path()));
    }

    #[test]
    fn converts_reference_inv3() {
        let dir = Path::new(REFERENCE);
        if !dir.join("main.plist").is_file() || !dir.join("matrix.dat").is_file() {
            eprintln!("skipping: {REFERENCE} is absent");
            return;
        }
        let v = convert_inv3_dir(dir).unwrap();
        assert_eq!(v.dims, [256, 256, 108]);
        assert!((v.spacing[0] - 0.9570312).abs() < 1e-6);
        assert!((v.spacing[1] - 0.9570312).abs() < 1e-6);
        assert!((v.spacing[2] - 1.5).abs() < 1e-12);
        assert_eq!(v.modality, Modality::Ct);
        assert_eq!(v.name, "ct-head");
        // main.plist claims a scalar range of -1024..3033 (the original series); the stored
        // matrix holds -1024..2986.
        let (lo, hi) = v.value_range();
        assert_eq!(lo, -1024.0);
        assert!((2000.0..=3033.0).contains(&hi), "max {hi}");
        assert_eq!(v.voxels.len(), v.voxel_count());
        assert_eq!(v.directions, CT_HEAD_DIRECTIONS);
        // The anterior direction (-y in LPS) is +j: the face (dense teeth at the bottom slices)
        // lies at large j.
        let bone_centroid_j = |k0: usize, k1: usize| {
            let (mut sum, mut n) = (0.0, 0.0);
            for k in k0..k1 {
                for j in 0..256 {
                    for i in 0..256 {
                        if v.voxels.get(v.index(i, j, k)) > 1500.0 {
                            sum += j as f64;
                            n += 1.0;
                        }
                    }
                }
            }
            sum / n
        };
        assert!(bone_centroid_j(0, 8) > 150.0, "{}", bone_centroid_j(0, 8));
    }

    #[test]
    fn missing_dir_errors() {
        let dir = std::env::temp_dir().join(format!("cao-xr-no-such-inv3-{}", std::process::id()));
        let e = convert_inv3_dir(&dir).unwrap_err().to_string();
        assert!(e.contains("main.plist"), "{e}");
    }
}
