//! Environment lights: an equirectangular image (PNG or Radiance HDR), a procedural studio or
//! sky, or a constant colour, and their projection to SH per colour channel.
//!
//! World frame: +Y up, the viewer looks along -Z (OpenXR), +X to the right.
//!
//! Equirectangular mapping of a world direction w = (x, y, z) to image coordinates (u, v) in
//! [0, 1] (u to the right, v down; texel (i, j) covers [i/W, (i+1)/W] x [j/H, (j+1)/H]):
//!
//! u = 0.5 + atan2(x, -z) / (2 pi),   v = acos(y) / pi
//!
//! and back, with phi = 2 pi (u - 0.5), theta = pi v:
//!
//! w = (sin(theta) sin(phi), cos(theta), -sin(theta) cos(phi)).
//!
//! So the image centre is straight ahead (-Z), u = 0.75 is +X (to the right, as a panorama seen
//! from inside), u = 0 and 1 are behind (+Z), the top row is +Y and the bottom row -Y.
//!
//! Images are not required to be 2:1 (any W x H is accepted and mapped as above), but must be at
//! least 8 x 4 texels. PNG samples are sRGB-decoded to linear (any alpha channel is ignored); HDR
//! values are taken as linear radiance (the EXPOSURE header is ignored).

use super::sh::{self, COEFFS_MAX};
use super::LightError;
use glam::{DMat3, DVec3};
use std::f64::consts::{PI, TAU};
use std::path::Path;
use std::sync::OnceLock;

/// The built-in procedural environments, for help texts.
pub const ENVIRONMENTS: &[&str] = &["studio", "sky"];

/// The largest sample table of an image: it is box-reduced to at most this many texels
/// (longitude x latitude) before projection, so [`Environment::project`] stays cheap.
const TABLE_MAX: (usize, usize) = (128, 64);

/// Quadrature of the procedural environments: 64 Gauss-Legendre latitudes x 128 longitudes.
const PROCEDURAL_GRID: (usize, usize) = (64, 128);

/// A distant light.
#[derive(Clone, Debug)]
pub enum Environment {
    /// An equirectangular image.
    Image(EquirectImage),
    /// A photo studio: soft key light from the upper front-left, a dimmer cool fill from the
    /// right, a warm floor bounce, dark grey walls.
    Studio,
    /// Outdoors: a blue-white sky dome, a sun with its glow high on the front-right, brown ground.
    Sky,
    /// The same linear radiance (R, G, B) from every direction.
    Constant([f32; 3]),
}

/// SH coefficients of a light per colour channel (R, G, B), L_k = integral of L(w) Y_k(w) dw in
/// the volume's data frame. See [`super::sh`] for the conventions.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShLight {
    pub coeffs: [[f32; COEFFS_MAX]; 3],
}

impl ShLight {
    /// sum_k V_k L_k per channel: the emission of a voxel of albedo 1 with visibility
    /// coefficients `vis` (multiply by the albedo for E).
    pub fn dot(&self, vis: &[f32; COEFFS_MAX]) -> [f32; 3] {
        self.coeffs
            .map(|c| c.iter().zip(vis).map(|(l, v)| l * v).sum::<f32>())
    }

    /// The band-limited radiance the coefficients stand for, in data-frame direction `d`.
    pub fn radiance(&self, d: DVec3) -> [f32; 3] {
        let y = sh::eval(d.normalize());
        self.coeffs
            .map(|c| c.iter().zip(y).map(|(l, y)| *l as f64 * y).sum::<f64>() as f32)
    }
}

/// One entry of a projection table: a world direction and radiance times solid angle.
#[derive(Clone, Copy, Debug)]
struct Sample {
    dir: DVec3,
    weighted: [f64; 3],
}

/// An equirectangular environment image in linear radiance, row 0 at the top (+Y).
#[derive(Clone, Debug)]
pub struct EquirectImage {
    width: usize,
    height: usize,
    pixels: Vec<[f32; 3]>,
    /// The image reduced to at most [`TABLE_MAX`] cells, each with its exact solid angle.
    samples: Vec<Sample>,
}

impl EquirectImage {
    /// An image from linear radiance, row-major with row 0 at the top. Refuses sizes below
    /// 8 x 4, a pixel count that does not match, and NaN, infinite or negative radiance.
    pub fn new(width: usize, height: usize, pixels: Vec<[f32; 3]>) -> Result<Self, LightError> {
        Self::build(width, height, pixels).map_err(|msg| LightError::Spec {
            spec: "environment image".into(),
            msg,
        })
    }

    fn build(width: usize, height: usize, pixels: Vec<[f32; 3]>) -> Result<Self, String> {
        check_size(width, height)?;
        if pixels.len() != width * height {
            return Err(format!(
                "{} pixels for a {width} x {height} image",
                pixels.len()
            ));
        }
        if let Some(i) = pixels
            .iter()
            .position(|p| p.iter().any(|c| !c.is_finite() || *c < 0.0))
        {
            return Err(format!(
                "pixel ({}, {}) has radiance {:?}: must be finite and >= 0",
                i % width,
                i / width,
                pixels[i]
            ));
        }
        let samples = reduce(width, height, &pixels);
        Ok(EquirectImage {
            width,
            height,
            pixels,
            samples,
        })
    }

    pub fn width(&self) -> usize {
        self.width
    }
    pub fn height(&self) -> usize {
        self.height
    }
    /// Linear radiance, row-major, row 0 at the top (+Y).
    pub fn pixels(&self) -> &[[f32; 3]] {
        &self.pixels
    }

    /// Bilinear radiance in world direction `w` (wrapping in longitude, clamped at the poles).
    pub fn radiance(&self, w: DVec3) -> [f32; 3] {
        let (u, v) = equirect_uv(w);
        let x = u * self.width as f64 - 0.5;
        let y = (v * self.height as f64 - 0.5).clamp(0.0, (self.height - 1) as f64);
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = ((x - x0) as f32, (y - y0) as f32);
        let w = self.width as i64;
        let i0 = (x0 as i64).rem_euclid(w) as usize;
        let i1 = (x0 as i64 + 1).rem_euclid(w) as usize;
        let j0 = y0 as usize;
        let j1 = (j0 + 1).min(self.height - 1);
        let p = |i: usize, j: usize| self.pixels[j * self.width + i];
        let mut out = [0.0; 3];
        for (c, o) in out.iter_mut().enumerate() {
            let top = p(i0, j0)[c] * (1.0 - fx) + p(i1, j0)[c] * fx;
            let bottom = p(i0, j1)[c] * (1.0 - fx) + p(i1, j1)[c] * fx;
            *o = top * (1.0 - fy) + bottom * fy;
        }
        out
    }

    /// Loads a `.png` (8 or 16 bit, gray/RGB with or without alpha, or palette).
    pub fn load_png(path: &Path) -> Result<Self, LightError> {
        let (w, h, px) = read_png(path)?;
        Self::build(w, h, px).map_err(|m| LightError::format(path, m))
    }

    /// Loads a Radiance `.hdr` (RGBE; flat, old-style or new-style run-length scanlines).
    pub fn load_hdr(path: &Path) -> Result<Self, LightError> {
        let data = std::fs::read(path).map_err(|source| LightError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let (w, h, px) = parse_hdr(&data).map_err(|e| match e {
            HdrError::Format(m) => LightError::format(path, m),
            HdrError::Unsupported(m) => LightError::unsupported(path, m),
        })?;
        Self::build(w, h, px).map_err(|m| LightError::format(path, m))
    }
}

fn check_size(width: usize, height: usize) -> Result<(), String> {
    if width < 8 || height < 4 {
        return Err(format!(
            "environment image is {width} x {height}: needs at least 8 x 4 texels"
        ));
    }
    Ok(())
}

/// (u, v) of a world direction (module doc).
pub fn equirect_uv(w: DVec3) -> (f64, f64) {
    let w = w.normalize();
    let u = 0.5 + w.x.atan2(-w.z) / TAU;
    let v = w.y.clamp(-1.0, 1.0).acos() / PI;
    (u, v)
}

/// World direction of image coordinates (u, v) (module doc).
pub fn equirect_dir(u: f64, v: f64) -> DVec3 {
    let (phi, theta) = (TAU * (u - 0.5), PI * v);
    DVec3::new(
        theta.sin() * phi.sin(),
        theta.cos(),
        -theta.sin() * phi.cos(),
    )
}

/// Box-reduces an image to at most [`TABLE_MAX`] cells. Each texel brings its exact solid angle
/// (2pi/W) * (cos(theta_top) - cos(theta_bottom)); a cell's direction is the luminance-weighted
/// mean of its texels' directions (the solid-angle-weighted one when it is black), so one bright
/// texel keeps its exact direction.
fn reduce(width: usize, height: usize, pixels: &[[f32; 3]]) -> Vec<Sample> {
    let (cw, ch) = (width.min(TABLE_MAX.0), height.min(TABLE_MAX.1));
    let mut rad = vec![[0.0f64; 3]; cw * ch];
    let mut dir_lum = vec![DVec3::ZERO; cw * ch];
    let mut dir_area = vec![DVec3::ZERO; cw * ch];
    let dphi = TAU / width as f64;
    for j in 0..height {
        let t0 = PI * j as f64 / height as f64;
        let t1 = PI * (j + 1) as f64 / height as f64;
        let omega = dphi * (t0.cos() - t1.cos());
        let v = (j as f64 + 0.5) / height as f64;
        let cj = j * ch / height;
        for i in 0..width {
            let d = equirect_dir((i as f64 + 0.5) / width as f64, v);
            let p = pixels[j * width + i];
            let c = cj * cw + i * cw / width;
            for (r, p) in rad[c].iter_mut().zip(p) {
                *r += p as f64 * omega;
            }
            let lum = 0.2126 * p[0] as f64 + 0.7152 * p[1] as f64 + 0.0722 * p[2] as f64;
            dir_lum[c] += d * (lum * omega);
            dir_area[c] += d * omega;
        }
    }
    (0..cw * ch)
        .map(|c| {
            let d = if dir_lum[c].length_squared() > 0.0 {
                dir_lum[c]
            } else {
                dir_area[c]
            };
            Sample {
                dir: d.normalize(),
                weighted: rad[c],
            }
        })
        .collect()
}

/// The quadrature table of a radiance function.
fn table_of(f: impl Fn(DVec3) -> [f64; 3], grid: (usize, usize)) -> Vec<Sample> {
    sh::sphere_quadrature(grid.0, grid.1)
        .into_iter()
        .map(|(dir, omega)| Sample {
            dir,
            weighted: f(dir).map(|r| r * omega),
        })
        .collect()
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

fn mix3(a: [f64; 3], b: [f64; 3], t: f64) -> [f64; 3] {
    [0, 1, 2].map(|c| a[c] + (b[c] - a[c]) * t)
}

/// Studio radiance in world direction `w` (unit). The sphere's mean radiance is about 1.2; an
/// unshadowed surface (half-space visibility) facing the key gets E / albedo of about 0.9, one
/// facing away about 0.3.
fn studio(w: DVec3) -> [f64; 3] {
    // The key comes from up, front (towards the viewer, +Z) and left.
    let key = DVec3::new(-1.0, 1.2, 1.0).normalize();
    let fill = DVec3::new(1.0, 0.15, 0.35).normalize();
    let k = 14.0 * w.dot(key).max(0.0).powi(8);
    let f = 2.5 * w.dot(fill).max(0.0).powi(4);
    let floor = 0.45 * smoothstep(0.0, 0.35, -w.y);
    let wall = 0.06;
    [
        wall + k * 1.0 + f * 0.80 + floor * 1.0,
        wall + k * 0.96 + f * 0.88 + floor * 0.72,
        wall + k * 0.90 + f * 1.00 + floor * 0.48,
    ]
}

/// Sky radiance in world direction `w` (unit). The sphere's mean radiance is about 0.9; an
/// unshadowed surface facing the sun gets E / albedo of about 0.7, one facing away about 0.2.
fn sky(w: DVec3) -> [f64; 3] {
    let sun = DVec3::new(0.45, 0.75, 0.35).normalize();
    let horizon = [0.95, 0.97, 1.0];
    let zenith = [0.35, 0.55, 1.0];
    let ground = [0.30, 0.21, 0.13];
    let up = w.y.max(0.0);
    let dome = mix3(horizon, zenith, up.sqrt()).map(|c| c * 1.1);
    // Blend to the ground over a few degrees below the horizon.
    let base = mix3(dome, ground, smoothstep(0.0, 0.06, -w.y));
    let c = w.dot(sun);
    let glow = 55.0 * ((c - 1.0) / 0.01).exp() + 2.0 * ((c - 1.0) / 0.15).exp();
    let sun_colour = [1.0, 0.93, 0.78];
    [0, 1, 2].map(|i| base[i] + glow * sun_colour[i])
}

fn studio_table() -> &'static [Sample] {
    static T: OnceLock<Vec<Sample>> = OnceLock::new();
    T.get_or_init(|| table_of(studio, PROCEDURAL_GRID))
}

fn sky_table() -> &'static [Sample] {
    static T: OnceLock<Vec<Sample>> = OnceLock::new();
    T.get_or_init(|| table_of(sky, PROCEDURAL_GRID))
}

impl Environment {
    /// "studio", "sky", "white" (= constant:1,1,1), "constant:R,G,B" or "constant:V" (linear
    /// radiance >= 0), or the path of an equirectangular `.png` or `.hdr` image.
    pub fn from_spec(spec: &str) -> Result<Environment, LightError> {
        let s = spec.trim();
        let lower = s.to_ascii_lowercase();
        let err = |msg: String| LightError::Spec {
            spec: spec.to_string(),
            msg,
        };
        match lower.as_str() {
            "studio" => return Ok(Environment::Studio),
            "sky" => return Ok(Environment::Sky),
            "white" => return Ok(Environment::Constant([1.0; 3])),
            _ => {}
        }
        if let Some(rest) = lower.strip_prefix("constant:") {
            let vals: Vec<f32> = rest
                .split(',')
                .map(|t| t.trim().parse::<f32>())
                .collect::<Result<_, _>>()
                .map_err(|e| err(format!("bad number in '{rest}': {e}")))?;
            let rgb = match vals[..] {
                [v] => [v; 3],
                [r, g, b] => [r, g, b],
                _ => return Err(err(format!("expected 1 or 3 values, got {}", vals.len()))),
            };
            if rgb.iter().any(|c| !c.is_finite() || *c < 0.0) {
                return Err(err("radiance must be finite and >= 0".into()));
            }
            return Ok(Environment::Constant(rgb));
        }
        let path = Path::new(s);
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref()
        {
            Some("png") => EquirectImage::load_png(path).map(Environment::Image),
            Some("hdr") | Some("pic") => EquirectImage::load_hdr(path).map(Environment::Image),
            _ => Err(err(format!(
                "expected {}, white, constant:R,G,B or an equirectangular .png/.hdr image",
                ENVIRONMENTS.join(", ")
            ))),
        }
    }

    /// Linear radiance arriving from world direction `w`.
    pub fn radiance(&self, w: DVec3) -> [f32; 3] {
        let w = w.normalize();
        match self {
            Environment::Image(img) => img.radiance(w),
            Environment::Studio => studio(w).map(|c| c as f32),
            Environment::Sky => sky(w).map(|c| c as f32),
            Environment::Constant(c) => *c,
        }
    }

    /// L_k = integral of L(w) * Y_k(normalize(data_from_world * w)) dw over world directions w:
    /// the light's SH coefficients in the volume's data frame. `data_from_world` should be a
    /// rotation (a uniform scale is harmless); turning the light or the volume is one more call
    /// with the new matrix. Costs about 16 x 3 multiply-adds per table entry (<= 8192 entries).
    pub fn project(&self, data_from_world: DMat3) -> ShLight {
        match self {
            Environment::Image(img) => project_samples(&img.samples, data_from_world),
            Environment::Studio => project_samples(studio_table(), data_from_world),
            Environment::Sky => project_samples(sky_table(), data_from_world),
            // Degree <= 3 integrands: a 4 x 8 product rule is exact.
            Environment::Constant(c) => {
                project_samples(&table_of(|_| c.map(|v| v as f64), (4, 8)), data_from_world)
            }
        }
    }
}

fn project_samples(samples: &[Sample], data_from_world: DMat3) -> ShLight {
    let mut acc = [[0.0f64; COEFFS_MAX]; 3];
    for s in samples {
        let y = sh::eval((data_from_world * s.dir).normalize_or_zero());
        for (a, w) in acc.iter_mut().zip(s.weighted) {
            for (a, y) in a.iter_mut().zip(y) {
                *a += w * y;
            }
        }
    }
    ShLight {
        coeffs: acc.map(|c| c.map(|v| v as f32)),
    }
}

/// sRGB transfer function, decoded to linear.
pub fn srgb_to_linear(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

fn read_png(path: &Path) -> Result<(usize, usize, Vec<[f32; 3]>), LightError> {
    let file = std::fs::File::open(path).map_err(|source| LightError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |e: png::DecodingError| LightError::format(path, format!("not a valid PNG: {e}"));
    let mut dec = png::Decoder::new_with_limits(
        std::io::BufReader::new(file),
        png::Limits { bytes: 1 << 30 },
    );
    // Palettes and low bit depths to 8 bits; 16-bit samples stay 16 bits.
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec.read_info().map_err(bad)?;
    let (w, h) = {
        let info = reader.info();
        (info.width as usize, info.height as usize)
    };
    check_size(w, h).map_err(|m| LightError::format(path, m))?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| LightError::format(path, "image too large"))?;
    let mut buf = vec![0u8; size];
    let out = reader.next_frame(&mut buf).map_err(bad)?;
    let channels = match out.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => {
            return Err(LightError::unsupported(path, "unexpanded palette"));
        }
    };
    let wide = out.bit_depth == png::BitDepth::Sixteen;
    let lut8: Vec<f32> = (0..256).map(|b| srgb_to_linear(b as f32 / 255.0)).collect();
    let sample = |row: &[u8], i: usize| -> f32 {
        if wide {
            srgb_to_linear(u16::from_be_bytes([row[2 * i], row[2 * i + 1]]) as f32 / 65535.0)
        } else {
            lut8[row[i] as usize]
        }
    };
    let mut px = Vec::with_capacity(w * h);
    for j in 0..h {
        let row = &buf[j * out.line_size..(j + 1) * out.line_size];
        for i in 0..w {
            let b = i * channels;
            px.push(if channels < 3 {
                [sample(row, b); 3]
            } else {
                [sample(row, b), sample(row, b + 1), sample(row, b + 2)]
            });
        }
    }
    Ok((w, h, px))
}

enum HdrError {
    Format(String),
    Unsupported(String),
}

/// A Radiance RGBE file to (width, height, linear pixels with row 0 at the top).
fn parse_hdr(data: &[u8]) -> Result<(usize, usize, Vec<[f32; 3]>), HdrError> {
    use HdrError::{Format, Unsupported};
    const HEADER_MAX: usize = 1 << 16;
    let mut pos = 0;
    let line = |pos: &mut usize| -> Result<String, HdrError> {
        let rest = &data[*pos..data.len().min(HEADER_MAX)];
        let n = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| Format("bad header: no end of line in the first 64 KiB".into()))?;
        *pos += n + 1;
        Ok(String::from_utf8_lossy(&rest[..n]).trim_end().to_string())
    };
    let magic = line(&mut pos)?;
    if !magic.starts_with("#?") {
        return Err(Format(
            "bad header: not a Radiance HDR file (no '#?RADIANCE' line)".into(),
        ));
    }
    loop {
        let l = line(&mut pos)?;
        if l.is_empty() {
            break;
        }
        if let Some(f) = l.strip_prefix("FORMAT=") {
            if f.trim() != "32-bit_rle_rgbe" {
                return Err(Unsupported(format!(
                    "pixel format '{}' (only 32-bit_rle_rgbe)",
                    f.trim()
                )));
            }
        }
    }
    let res = line(&mut pos)?;
    let t: Vec<&str> = res.split_whitespace().collect();
    let bad_res = || Format(format!("bad resolution line '{res}'"));
    if t.len() != 4 {
        return Err(bad_res());
    }
    if !matches!(t[0], "-Y" | "+Y") || !matches!(t[2], "+X" | "-X") {
        return Err(Unsupported(format!(
            "orientation '{res}' (only -Y/+Y H +X/-X W)"
        )));
    }
    let h: usize = t[1].parse().map_err(|_| bad_res())?;
    let w: usize = t[3].parse().map_err(|_| bad_res())?;
    check_size(w, h).map_err(Format)?;
    if w.checked_mul(h).is_none_or(|n| n > 1 << 28) {
        return Err(Format(format!("image of {w} x {h} is too large")));
    }
    let (flip_y, flip_x) = (t[0] == "+Y", t[2] == "-X");

    let truncated = |j: usize| Format(format!("truncated at scanline {j} of {h}"));
    let mut rgbe = vec![[0u8; 4]; w];
    // Grown row by row, so a header promising a huge image on a short file fails cheaply.
    let mut px: Vec<[f32; 3]> = Vec::new();
    for j in 0..h {
        let head = data.get(pos..pos + 4).ok_or_else(|| truncated(j))?;
        if (8..=0x7fff).contains(&w) && head[0] == 2 && head[1] == 2 && head[2] & 0x80 == 0 {
            // New-style RLE: the four components one after the other, each in runs.
            let n = ((head[2] as usize) << 8) | head[3] as usize;
            if n != w {
                return Err(Format(format!(
                    "scanline {j} says width {n}, the header {w}"
                )));
            }
            pos += 4;
            for c in 0..4 {
                let mut x = 0;
                while x < w {
                    let &count = data.get(pos).ok_or_else(|| truncated(j))?;
                    pos += 1;
                    if count > 128 {
                        let n = (count - 128) as usize;
                        let &v = data.get(pos).ok_or_else(|| truncated(j))?;
                        pos += 1;
                        if x + n > w {
                            return Err(Format(format!("run overflows scanline {j}")));
                        }
                        rgbe[x..x + n].iter_mut().for_each(|p| p[c] = v);
                        x += n;
                    } else {
                        let n = count as usize;
                        if n == 0 || x + n > w {
                            return Err(Format(format!("bad run length {n} in scanline {j}")));
                        }
                        let lit = data.get(pos..pos + n).ok_or_else(|| truncated(j))?;
                        pos += n;
                        for (p, &v) in rgbe[x..x + n].iter_mut().zip(lit) {
                            p[c] = v;
                        }
                        x += n;
                    }
                }
            }
        } else {
            // Flat pixels, possibly with old-style runs (1, 1, 1, n): repeat the previous pixel.
            let mut x = 0;
            let mut shift = 0;
            while x < w {
                let p = data.get(pos..pos + 4).ok_or_else(|| truncated(j))?;
                pos += 4;
                if p[0] == 1 && p[1] == 1 && p[2] == 1 {
                    let n = (p[3] as usize) << shift;
                    if x == 0 || x + n > w {
                        return Err(Format(format!("bad old-style run in scanline {j}")));
                    }
                    let prev = rgbe[x - 1];
                    rgbe[x..x + n].fill(prev);
                    x += n;
                    shift += 8;
                } else {
                    rgbe[x] = [p[0], p[1], p[2], p[3]];
                    x += 1;
                    shift = 0;
                }
            }
        }
        let start = px.len();
        px.extend(rgbe.iter().map(|p| rgbe_to_f32(*p)));
        if flip_x {
            px[start..].reverse();
        }
    }
    if flip_y {
        // Rows were read bottom-up.
        let rows: Vec<&[[f32; 3]]> = px.chunks(w).rev().collect();
        px = rows.concat();
    }
    Ok((w, h, px))
}

fn rgbe_to_f32(p: [u8; 4]) -> [f32; 3] {
    if p[3] == 0 {
        return [0.0; 3];
    }
    let f = 2f64.powi(p[3] as i32 - 136);
    [0, 1, 2].map(|c| (p[c] as f64 * f) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::test_rng::Rng;
    use crate::volume::test_scratch::Scratch;

    const SQRT_4PI: f64 = 3.544_907_701_811_032;

    /// A rotation from an axis and angle.
    fn rot(axis: DVec3, angle: f64) -> DMat3 {
        DMat3::from_axis_angle(axis.normalize(), angle)
    }

    fn rotations() -> Vec<DMat3> {
        let mut rng = Rng::new(99);
        let mut r = vec![DMat3::IDENTITY, rot(DVec3::Y, 0.7), rot(DVec3::X, -2.0)];
        r.extend((0..3).map(|_| rot(rng.unit(), 6.0 * rng.f64())));
        r
    }

    /// The light's reconstructed radiance at world direction w, projected with `m`.
    fn recon(l: &ShLight, m: DMat3, w: DVec3) -> [f32; 3] {
        l.radiance(m * w)
    }

    #[test]
    fn equirect_mapping_round_trips_and_faces_forward() {
        let (u, v) = equirect_uv(-DVec3::Z);
        assert!((u - 0.5).abs() < 1e-12 && (v - 0.5).abs() < 1e-12);
        let (u, _) = equirect_uv(DVec3::X);
        assert!((u - 0.75).abs() < 1e-12, "+X is right of centre");
        assert!(equirect_uv(DVec3::Y).1.abs() < 1e-12, "top row is up");
        let mut rng = Rng::new(1);
        for _ in 0..50 {
            let w = rng.unit();
            let (u, v) = equirect_uv(w);
            assert!((equirect_dir(u, v) - w).length() < 1e-12);
        }
    }

    #[test]
    fn constant_environment_projects_to_band_zero() {
        let c = [0.25f32, 1.5, 3.0];
        let env = Environment::from_spec("constant:0.25, 1.5,3").unwrap();
        for m in rotations() {
            let l = env.project(m);
            for (lc, c) in l.coeffs.iter().zip(c) {
                let want = c as f64 * SQRT_4PI;
                let got = lc[0] as f64;
                assert!((got - want).abs() <= 1e-6 * want, "{got} vs {want}");
                for (k, v) in lc.iter().enumerate().skip(1) {
                    assert!((*v as f64).abs() <= 1e-6 * want, "k = {k}");
                }
            }
            // An empty volume: V_k = Y_0 delta_k0, so E / albedo = c exactly.
            let mut vis = [0.0f32; COEFFS_MAX];
            vis[0] = sh::Y0 as f32;
            let e = l.dot(&vis);
            for ch in 0..3 {
                assert!((e[ch] - c[ch]).abs() <= 1e-6 * c[ch], "{e:?} vs {c:?}");
            }
        }
        let white = Environment::from_spec("WHITE")
            .unwrap()
            .project(DMat3::IDENTITY);
        assert!((white.coeffs[1][0] as f64 - SQRT_4PI).abs() < 1e-6);
    }

    #[test]
    fn constant_image_projects_to_band_zero() {
        // Sizes that reduce evenly, unevenly and not at all.
        for (w, h) in [(512, 256), (300, 77), (64, 32)] {
            let img = EquirectImage::new(w, h, vec![[0.5, 1.0, 2.0]; w * h]).unwrap();
            let env = Environment::Image(img);
            for m in rotations() {
                let l = env.project(m);
                for (ch, c) in [0.5, 1.0, 2.0].into_iter().enumerate() {
                    let want = c * SQRT_4PI;
                    let got = l.coeffs[ch][0] as f64;
                    assert!(
                        (got - want).abs() <= 1e-5 * want,
                        "{w}x{h}: {got} vs {want}"
                    );
                    for k in 1..COEFFS_MAX {
                        let v = l.coeffs[ch][k] as f64;
                        assert!(v.abs() <= 1e-3 * want, "{w}x{h} k = {k}: {v}");
                    }
                }
            }
        }
    }

    /// An image of background `bg` with texel (i, j) set to `hot`.
    fn one_texel(w: usize, h: usize, i: usize, j: usize, bg: f32, hot: [f32; 3]) -> EquirectImage {
        let mut px = vec![[bg; 3]; w * h];
        px[j * w + i] = hot;
        EquirectImage::new(w, h, px).unwrap()
    }

    #[test]
    fn one_bright_texel_projects_to_its_direction_rotated() {
        let (w, h, i, j) = (32, 16, 21, 5);
        let hot = [4.0f32, 2.0, 1.0];
        let env = Environment::Image(one_texel(w, h, i, j, 0.0, hot));
        let dir = equirect_dir((i as f64 + 0.5) / w as f64, (j as f64 + 0.5) / h as f64);
        let t0 = PI * j as f64 / h as f64;
        let t1 = PI * (j + 1) as f64 / h as f64;
        let omega = TAU / w as f64 * (t0.cos() - t1.cos());
        for m in rotations() {
            let l = env.project(m);
            let y = sh::eval(m * dir);
            for (lc, hot) in l.coeffs.iter().zip(hot) {
                for (k, (got, y)) in lc.iter().zip(y).enumerate() {
                    let want = hot as f64 * omega * y;
                    let got = *got as f64;
                    assert!((got - want).abs() < 1e-6, "k = {k}: {got} vs {want}");
                }
            }
        }
        // Reduced (256 x 128 -> 128 x 64), the texel keeps its direction and its energy.
        let env = Environment::Image(one_texel(256, 128, 170, 40, 0.0, hot));
        let dir = equirect_dir(170.5 / 256.0, 40.5 / 128.0);
        let t0 = PI * 40.0 / 128.0;
        let t1 = PI * 41.0 / 128.0;
        let omega = TAU / 256.0 * (t0.cos() - t1.cos());
        let m = rotations()[4];
        let l = env.project(m);
        let y = sh::eval(m * dir);
        for (k, (got, y)) in l.coeffs[0].iter().zip(y).enumerate() {
            let want = hot[0] as f64 * omega * y;
            assert!((*got as f64 - want).abs() < 1e-7, "k = {k}");
        }
    }

    #[test]
    fn rotating_the_frame_rotates_the_light() {
        // Projecting with data_from_world = R and reading at R w gives what the unrotated
        // projection gives at w: a constant plus one bright texel (exact), and the studio.
        let img = Environment::Image(one_texel(64, 32, 40, 9, 0.3, [9.0, 5.0, 2.0]));
        let mut rng = Rng::new(17);
        for (env, tol) in [
            (img, 1e-5),
            (Environment::Studio, 2e-3),
            (Environment::Sky, 2e-3),
        ] {
            let base = env.project(DMat3::IDENTITY);
            let scale = base.coeffs[1][0].abs();
            for m in rotations() {
                let l = env.project(m);
                for _ in 0..10 {
                    let w = rng.unit();
                    let a = recon(&l, m, w);
                    let b = recon(&base, DMat3::IDENTITY, w);
                    for ch in 0..3 {
                        assert!(
                            (a[ch] - b[ch]).abs() <= tol * scale,
                            "{env:?} at {w}: {a:?} vs {b:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn empty_volume_emission_is_the_mean_radiance() {
        // E / albedo for V = 1 is (1/4pi) * integral of L: check the procedural tables against
        // a finer independent integration of the same function.
        for env in [Environment::Studio, Environment::Sky] {
            let mut vis = [0.0f32; COEFFS_MAX];
            vis[0] = sh::Y0 as f32;
            let e = env.project(rot(DVec3::Z, 1.0)).dot(&vis);
            for (ch, e) in e.into_iter().enumerate() {
                let mean = sh::project_fn(|w| env.radiance(w)[ch] as f64, 200_000)[0] / SQRT_4PI;
                assert!(
                    (e as f64 - mean).abs() < 2e-3 * mean,
                    "{env:?} channel {ch}: {e} vs {mean}"
                );
                assert!((0.3..2.0).contains(&mean), "{env:?}: mean radiance {mean}");
            }
        }
    }

    #[test]
    fn procedural_lights_come_from_where_they_say() {
        let lum = |c: [f32; 3]| 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2];
        let s = |x, y, z| Environment::Studio.radiance(DVec3::new(x, y, z));
        // Key from upper front-left (the viewer is at +Z), fill from the right.
        assert!(lum(s(-1.0, 1.2, 1.0)) > 5.0 * lum(s(1.0, 1.2, 1.0)));
        assert!(lum(s(1.0, 0.1, 0.3)) > 3.0 * lum(s(-1.0, 0.1, -0.3)));
        assert!(
            lum(s(-1.0, 1.2, 1.0)) > 2.0 * lum(s(1.0, 0.1, 0.3)),
            "fill is dimmer"
        );
        let floor = s(0.0, -1.0, 0.0);
        assert!(
            floor[0] > floor[2] && lum(floor) > lum(s(0.0, 0.0, -1.0)),
            "warm floor"
        );
        let k = Environment::Sky;
        let up = k.radiance(DVec3::Y);
        let down = k.radiance(-DVec3::Y);
        assert!(up[2] > up[0], "blue sky {up:?}");
        assert!(
            down[0] > down[2] && lum(down) < lum(up),
            "brown ground {down:?}"
        );
        // The band-limited light keeps the key's side brighter in the data frame too.
        let l = Environment::Studio.project(DMat3::IDENTITY);
        assert!(
            lum(l.radiance(DVec3::new(-1.0, 1.2, 1.0)))
                > lum(l.radiance(DVec3::new(1.0, -1.0, -1.0)))
        );
    }

    fn write_png(
        path: &Path,
        w: u32,
        h: u32,
        color: png::ColorType,
        depth: png::BitDepth,
        data: &[u8],
    ) {
        let file = std::fs::File::create(path).unwrap();
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), w, h);
        enc.set_color(color);
        enc.set_depth(depth);
        enc.write_header().unwrap().write_image_data(data).unwrap();
    }

    #[test]
    fn png_loads_as_the_same_image_in_linear_radiance() {
        let dir = Scratch::new("light-png");
        let (w, h) = (24usize, 12usize);
        let mut rgb = Vec::new();
        for j in 0..h {
            for i in 0..w {
                rgb.extend([(i * 10) as u8, (j * 20) as u8, ((i * j) % 256) as u8]);
            }
        }
        let path = dir.file("env.png");
        write_png(
            &path,
            w as u32,
            h as u32,
            png::ColorType::Rgb,
            png::BitDepth::Eight,
            &rgb,
        );
        let loaded = Environment::from_spec(path.to_str().unwrap()).unwrap();
        let Environment::Image(img) = &loaded else {
            panic!("not an image")
        };
        let px: Vec<[f32; 3]> = rgb
            .chunks(3)
            .map(|c| [0, 1, 2].map(|k| srgb_to_linear(c[k] as f32 / 255.0)))
            .collect();
        assert_eq!(img.pixels(), &px[..]);
        assert_eq!(
            img.pixels()[w + 1],
            [
                srgb_to_linear(10.0 / 255.0),
                srgb_to_linear(20.0 / 255.0),
                srgb_to_linear(1.0 / 255.0)
            ]
        );
        let direct = Environment::Image(EquirectImage::new(w, h, px).unwrap());
        let m = rotations()[3];
        assert_eq!(loaded.project(m), direct.project(m));
        assert!((srgb_to_linear(1.0) - 1.0).abs() < 1e-6);
        assert!((srgb_to_linear(128.0 / 255.0) - 0.215_860_5).abs() < 1e-6);

        // 16-bit grey with alpha: the alpha is ignored, grey fills all channels.
        let mut ga = Vec::new();
        for j in 0..h {
            for i in 0..w {
                let g = (i * 2000 + j * 300) as u16;
                ga.extend(g.to_be_bytes());
                ga.extend(7u16.to_be_bytes());
            }
        }
        let path = dir.file("grey16.PNG");
        write_png(
            &path,
            w as u32,
            h as u32,
            png::ColorType::GrayscaleAlpha,
            png::BitDepth::Sixteen,
            &ga,
        );
        let Environment::Image(img) = Environment::from_spec(path.to_str().unwrap()).unwrap()
        else {
            panic!("not an image")
        };
        let g = srgb_to_linear((5 * 2000 + 3 * 300) as f32 / 65535.0);
        assert_eq!(img.pixels()[3 * w + 5], [g; 3]);
    }

    /// RGBE of a linear colour (Ward's encoding: shared exponent of the largest channel).
    fn to_rgbe(c: [f32; 3]) -> [u8; 4] {
        let m = c[0].max(c[1]).max(c[2]);
        if m < 1e-32 {
            return [0; 4];
        }
        let e = m.log2().floor() as i32 + 1;
        let scale = 256.0 / 2f32.powi(e);
        [
            (c[0] * scale) as u8,
            (c[1] * scale) as u8,
            (c[2] * scale) as u8,
            (e + 128) as u8,
        ]
    }

    /// New-style RLE of one component row: runs of >= 3 equal bytes, literals otherwise.
    fn rle_component(v: &[u8], out: &mut Vec<u8>) {
        let mut x = 0;
        while x < v.len() {
            let mut run = 1;
            while x + run < v.len() && run < 127 && v[x + run] == v[x] {
                run += 1;
            }
            if run >= 3 {
                out.extend([128 + run as u8, v[x]]);
                x += run;
                continue;
            }
            let st = x;
            while x < v.len() && x - st < 128 {
                if x + 2 < v.len() && v[x] == v[x + 1] && v[x] == v[x + 2] {
                    break;
                }
                x += 1;
            }
            out.push((x - st) as u8);
            out.extend(&v[st..x]);
        }
    }

    fn write_hdr(w: usize, h: usize, px: &[[f32; 3]], rle: bool, res: &str) -> Vec<u8> {
        let mut out =
            format!("#?RADIANCE\n# test\nFORMAT=32-bit_rle_rgbe\nEXPOSURE=1.0\n\n{res}\n")
                .into_bytes();
        for j in 0..h {
            let row: Vec<[u8; 4]> = px[j * w..(j + 1) * w].iter().map(|c| to_rgbe(*c)).collect();
            if rle {
                out.extend([2, 2, (w >> 8) as u8, (w & 0xff) as u8]);
                for c in 0..4 {
                    let comp: Vec<u8> = row.iter().map(|p| p[c]).collect();
                    rle_component(&comp, &mut out);
                }
            } else {
                row.iter().for_each(|p| out.extend(p));
            }
        }
        out
    }

    /// A test image: values exactly representable in RGBE, with runs and gradients.
    fn hdr_pixels(w: usize, h: usize) -> Vec<[f32; 3]> {
        (0..w * h)
            .map(|n| {
                let (i, j) = (n % w, n / w);
                if j % 3 == 0 {
                    [2.0, 1.0, 0.5] // long runs
                } else {
                    [
                        i as f32 * 0.25,
                        j as f32 * 0.125 + 0.125,
                        1.0 / 64.0 * (1 + i % 4) as f32,
                    ]
                }
            })
            .collect()
    }

    #[test]
    fn hdr_loads_flat_and_rle() {
        let dir = Scratch::new("light-hdr");
        let (w, h) = (40, 20);
        let px = hdr_pixels(w, h);
        for (name, rle) in [("flat.hdr", false), ("rle.hdr", true)] {
            let path = dir.file(name);
            std::fs::write(&path, write_hdr(w, h, &px, rle, &format!("-Y {h} +X {w}"))).unwrap();
            let Environment::Image(img) = Environment::from_spec(path.to_str().unwrap()).unwrap()
            else {
                panic!("not an image")
            };
            assert_eq!((img.width(), img.height()), (w, h));
            for (n, (got, want)) in img.pixels().iter().zip(&px).enumerate() {
                let m = want[0].max(want[1]).max(want[2]);
                for c in 0..3 {
                    // Exact where the mantissa holds the value, else within RGBE's precision.
                    assert!(
                        (got[c] - want[c]).abs() <= m / 128.0,
                        "{name} pixel {n}: {got:?} vs {want:?}"
                    );
                }
            }
            assert_eq!(img.pixels()[0], [2.0, 1.0, 0.5]);
            assert_eq!(img.pixels()[w + 6], [1.5, 0.25, 3.0 / 64.0]);
        }
        // Bottom-up rows, or right-to-left columns: the same image read back the right way.
        let reference = EquirectImage::load_hdr(&dir.file("rle.hdr")).unwrap();
        let mut up = Vec::new();
        let mut mirrored = Vec::new();
        for j in 0..h {
            up.extend_from_slice(&px[(h - 1 - j) * w..(h - j) * w]);
            mirrored.extend(px[j * w..(j + 1) * w].iter().rev());
        }
        for (name, data, res) in [
            ("up.hdr", &up, format!("+Y {h} +X {w}")),
            ("mirrored.hdr", &mirrored, format!("-Y {h} -X {w}")),
        ] {
            let path = dir.file(name);
            std::fs::write(&path, write_hdr(w, h, data, true, &res)).unwrap();
            let img = EquirectImage::load_hdr(&path).unwrap();
            assert_eq!(img.pixels(), reference.pixels(), "{name}");
        }
        let img = &reference;
        assert_eq!(img.pixels()[w + 6], [1.5, 0.25, 3.0 / 64.0]);
        // Old-style runs: a pixel, then (1, 1, 1, n) repeats it n times.
        let mut data = b"#?RGBE\n\n-Y 4 +X 8\n".to_vec();
        for _ in 0..4 {
            data.extend([128, 64, 32, 129, 1, 1, 1, 7]);
        }
        let path = dir.file("old.hdr");
        std::fs::write(&path, data).unwrap();
        let img = EquirectImage::load_hdr(&path).unwrap();
        assert!(img.pixels().iter().all(|p| *p == [1.0, 0.5, 0.25]));
    }

    fn err_of(spec: &str) -> String {
        match Environment::from_spec(spec) {
            Ok(e) => panic!("{spec} loaded as {e:?}"),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn bad_specs_and_files_name_the_file_and_the_problem() {
        let dir = Scratch::new("light-bad");
        let (w, h) = (16, 8);
        let px = hdr_pixels(w, h);
        let good = write_hdr(w, h, &px, true, &format!("-Y {h} +X {w}"));
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            (
                "truncated.hdr",
                good[..good.len() - 10].to_vec(),
                "truncated at scanline 7",
            ),
            (
                "flat-truncated.hdr",
                write_hdr(w, h, &px, false, "-Y 8 +X 16")[..100].to_vec(),
                "truncated",
            ),
            ("magic.hdr", b"P6\n16 8\n255\n".to_vec(), "bad header"),
            (
                "noend.hdr",
                b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe".to_vec(),
                "bad header",
            ),
            (
                "res.hdr",
                b"#?RADIANCE\n\n-Y x +X 16\n".to_vec(),
                "bad resolution line",
            ),
            (
                "xyze.hdr",
                b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 8 +X 16\n".to_vec(),
                "unsupported: pixel format",
            ),
            (
                "rot.hdr",
                b"#?RADIANCE\n\n+X 16 -Y 8\n".to_vec(),
                "unsupported: orientation",
            ),
            (
                "small.hdr",
                write_hdr(4, 2, &px[..8], false, "-Y 2 +X 4"),
                "needs at least 8 x 4",
            ),
            (
                "huge.hdr",
                b"#?RADIANCE\n\n-Y 100000 +X 100000\n".to_vec(),
                "too large",
            ),
            (
                "garbage.png",
                b"\x89PNG\r\n\x1a\nnot really".to_vec(),
                "not a valid PNG",
            ),
        ];
        for (name, data, want) in cases {
            let path = dir.file(name);
            std::fs::write(&path, data).unwrap();
            let msg = err_of(path.to_str().unwrap());
            assert!(msg.contains(name) && msg.contains(want), "{name}: '{msg}'");
        }
        let path = dir.file("tiny.png");
        write_png(
            &path,
            4,
            2,
            png::ColorType::Rgb,
            png::BitDepth::Eight,
            &[0; 24],
        );
        let msg = err_of(path.to_str().unwrap());
        assert!(msg.contains("tiny.png") && msg.contains("4 x 2"), "{msg}");
        let missing = dir.file("missing.hdr");
        let msg = err_of(missing.to_str().unwrap());
        assert!(msg.contains("missing.hdr"), "{msg}");

        for (spec, want) in [
            ("constant:1,2", "expected 1 or 3 values"),
            ("constant:a,b,c", "bad number"),
            ("constant:-1", "finite and >= 0"),
            ("constant:nan", "finite and >= 0"),
            ("sunset", "expected studio, sky, white"),
            ("env.exr", "expected studio, sky, white"),
        ] {
            let msg = err_of(spec);
            assert!(msg.contains(spec) && msg.contains(want), "{spec}: '{msg}'");
        }
        for (px, want) in [
            (vec![[f32::NAN, 0.0, 0.0]; 32], "finite"),
            (vec![[0.0, -1.0, 0.0]; 32], ">= 0"),
            (vec![[0.0; 3]; 31], "31 pixels"),
        ] {
            let msg = EquirectImage::new(8, 4, px).unwrap_err().to_string();
            assert!(msg.contains(want), "{msg}");
        }
    }

    #[test]
    fn projection_is_cheap() {
        // No timing assert (shared CI machines); prints the cost for the record.
        let env =
            Environment::Image(EquirectImage::new(256, 128, vec![[1.0; 3]; 256 * 128]).unwrap());
        let _ = Environment::Studio.project(DMat3::IDENTITY);
        let t = std::time::Instant::now();
        let n = 20;
        for i in 0..n {
            std::hint::black_box(env.project(rot(DVec3::Y, i as f64)));
        }
        eprintln!(
            "project(8192 samples): {:.3} ms",
            t.elapsed().as_secs_f64() * 1e3 / n as f64
        );
    }
}
