//! Cross-scale synthetic scenes whose ground truth does not come from the model (`xscale synth`).
//!
//! A scene is a fine "true" surface (terrain heightfield + box buildings, `surface.rs`) with a
//! procedural multi-octave albedo and Blinn–Phong shading (`shade.rs`), photographed by an
//! aerial ring and by close-ups ≥ 20× closer (`cameras.rs`). Ground-truth images are ray-cast
//! from the true surface with its own exact intersection, 16 rays per pixel (`render.rs`). The
//! training pipeline gets a *proxy* mesh instead (`proxy.rs`): the terrain resampled at 1/8
//! resolution, buildings slightly shifted, and a low-frequency displacement of ~0.3% of the
//! scene size — like an MVS reconstruction. `output.rs` writes the scene directory in every
//! layout the loaders read.
//!
//! Everything is a pure function of `(preset, seed)`: same seed → byte-identical files.
//! World frame: z up, metres, terrain centred on the origin.

pub mod cameras;
pub mod noise;
pub mod output;
pub mod perturb;
pub mod proxy;
pub mod render;
pub mod shade;
pub mod surface;

use crate::rng::{self, Purpose};
use crate::scene::{Image, Mesh};
use cameras::{CameraParams, Placed, ViewKind};
use glam::{DVec2, DVec3};
use noise::stream;
use shade::{Look, Shader};
use std::path::Path;
use surface::{Building, Heightfield, TrueSurface};

/// Named parameter sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// 8 views (4 aerial, 4 close-up) at 64×48: unit tests and the committed fixture.
    Tiny,
    /// 40 views (24 aerial, 16 close-up) at 200×150. Its finest texture is tied to the `cpu`
    /// preset's finest hash level (at least 2.5 of its cells), so it measures what that model can
    /// learn, not how far a model's resolution reaches: it cannot show that a grid too coarse for
    /// the close-ups blurs them.
    Small,
    /// 56 views (28 aerial, 28 close-up in 7 clusters of 4: walls, roofs, pavement and grass, each
    /// with a held-out close-up) at 200×150,
    /// with the exact mesh, and texture detail that reaches 2.5× the close-ups' nominal pixel
    /// footprint whatever a model's settings (tiles 5×, grain 2.5×): it measures how far a model
    /// reaches across scales. Aerial and close-up footprints are ~30× apart (medians).
    Cross,
    /// 104 views (64 aerial, 40 close-up) at 1024×768: 81.8 million pixels, one ray per pixel
    /// (cheap), COLMAP and transforms.json layouts only (no MVSNet copy of the images). For
    /// memory and throughput at size, not for quality.
    Large,
}

impl Preset {
    pub fn name(self) -> &'static str {
        match self {
            Preset::Tiny => "tiny",
            Preset::Small => "small",
            Preset::Cross => "cross",
            Preset::Large => "large",
        }
    }
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct TerrainParams {
    /// The terrain covers [-half_size, half_size]² (m).
    pub half_size: f64,
    /// Cells per side of the true heightfield (multiple of 8).
    pub cells: usize,
    /// Height octaves `[wavelength, amplitude]` (m); heights are Σ amplitude·2·(noise − 0.5).
    pub octaves: Vec<[f64; 2]>,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct BuildingParams {
    pub count: usize,
    /// Footprint centres lie within this half-width of the origin (m).
    pub region: f64,
    /// Footprint side range (m).
    pub side: [f64; 2],
    /// Height range above the highest terrain under the footprint (m).
    pub height: [f64; 2],
    /// Minimum gap between footprints (m).
    pub gap: f64,
}

#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ProxyParams {
    /// The proxy terrain keeps every `stride`-th vertex of the true one.
    pub stride: usize,
    /// Amplitude of the low-frequency vertical displacement of the proxy terrain (m).
    pub displacement: f64,
    /// Wavelength of that displacement (m).
    pub displacement_wavelength: f64,
    /// Each proxy building is shifted by up to this much along each axis (m).
    pub building_shift: f64,
}

/// Every parameter of a generated scene (recorded in `synth.toml`).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Params {
    pub terrain: TerrainParams,
    pub buildings: BuildingParams,
    pub look: Look,
    pub cameras: CameraParams,
    pub proxy: ProxyParams,
    /// Rays per pixel = spp_side² (stratified grid, box filter).
    pub spp_side: u32,
    /// The lens of every camera (omitted from `synth.toml` for a pinhole).
    #[serde(skip_serializing_if = "Lens::is_pinhole")]
    pub lens: Lens,
}

/// The lens of a synthetic scene's cameras (`xscale synth --lens`): the views are placed as
/// with a pinhole (same poses and intrinsics), then rendered through the lens, and the cameras
/// are written with it (COLMAP OPENCV).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Lens {
    /// No distortion.
    #[default]
    Pinhole,
    /// OPENCV k1 = −0.2, k2 = 0.05, p1 = 0.001, p2 = −0.0015: a phone lens's barrel distortion
    /// (at 60° horizontal field of view a 4:3 image's corners move ≈ 7 % of their distance to
    /// the centre).
    Opencv,
}

impl Lens {
    pub fn is_pinhole(&self) -> bool {
        *self == Lens::Pinhole
    }

    pub fn name(&self) -> &'static str {
        match self {
            Lens::Pinhole => "pinhole",
            Lens::Opencv => "opencv",
        }
    }

    pub fn distortion(&self) -> crate::scene::Distortion {
        match self {
            Lens::Pinhole => crate::scene::Distortion::None,
            Lens::Opencv => crate::scene::Distortion::OpenCv {
                k1: -0.2,
                k2: 0.05,
                p1: 0.001,
                p2: -0.0015,
            },
        }
    }
}

impl Params {
    pub fn preset(p: Preset) -> Params {
        let (width, height, n_aerial, n_close, cells, close_cluster) = match p {
            Preset::Tiny => (64, 48, 4, 4, 256, 1),
            Preset::Small => (200, 150, 24, 16, 512, 4),
            Preset::Cross => (200, 150, 28, 28, 512, 4),
            Preset::Large => (1024, 768, 64, 40, 512, 4),
        };
        let hfov_deg = 60.0;
        let aerial_distance = 120.0;
        // Close-ups at 1/30 of the aerial distance (≤ 1/20 required): per-view median footprints then differ ≥ 20× too.
        let close_distance = aerial_distance / 30.0;
        let (fx, _, _, _) = cameras::intrinsics(width, height, hfov_deg);
        // Fine pattern period: 3× the nominal close-up pixel footprint (tiny), 5× (`cross`: its
        // grain at half the period is 2.5 close-up pixels, the finest detail the cameras see
        // whatever the model), or — for `small`,
        // the training benchmark — at least 2.5 cells of the `cpu` preset's finest hash level
        // (2048 cells across the 200 m scene, 0.24 m), so the benchmark measures what can be
        // learnt, not detail below the model's resolution. Aerial views (0.65 m footprint) still
        // cannot resolve it; close-ups see it at ~10 pixels per period.
        let fine_period = match p {
            Preset::Tiny => 3.0 * close_distance / fx,
            Preset::Cross => 5.0 * close_distance / fx,
            Preset::Small | Preset::Large => (3.0 * close_distance / fx).max(2.5 * 200.0 / 2048.0),
        };
        let el: f64 = 50.0f64.to_radians();
        let az: f64 = 35.0f64.to_radians();
        Params {
            terrain: TerrainParams {
                half_size: 100.0,
                cells,
                octaves: vec![[70.0, 4.0], [18.0, 1.0], [5.0, 0.3]],
            },
            buildings: BuildingParams {
                count: 7,
                region: 35.0,
                side: [8.0, 16.0],
                height: [6.0, 16.0],
                gap: 4.0,
            },
            look: Look {
                coarse_wavelength: 32.0,
                mid_wavelength: 6.0,
                fine_period,
                sun_dir: [el.cos() * az.cos(), el.cos() * az.sin(), el.sin()],
                sun: 0.75,
                ambient: 0.35,
            },
            cameras: CameraParams {
                width,
                height,
                hfov_deg,
                n_aerial,
                n_close,
                aerial_distance,
                aerial_elevation_deg: [55.0, 70.0],
                aerial_target_jitter: 10.0,
                close_distance,
                close_region: 40.0,
                close_cluster,
                min_hit_fraction: 0.97,
                close_by_material: p == Preset::Cross,
            },
            // The proxy: `tiny` is a coarse, visibly displaced reconstruction (1/8 resolution,
            // ±0.6 m ≈ an aerial pixel). `small` is what an MVS run that used the close-ups
            // would give: 1/2 resolution, ±5 cm (≈ 2 close-up pixels), so a held-out close-up's
            // surface is consistent with its training neighbours to a few of their pixels.
            // `cross` gets the exact surface (full resolution, no displacement, no shift): it
            // measures reach across scales, not the cost of a wrong mesh.
            proxy: match p {
                Preset::Cross => ProxyParams {
                    stride: 1,
                    displacement: 0.0,
                    displacement_wavelength: 60.0,
                    building_shift: 0.0,
                },
                Preset::Tiny => ProxyParams {
                    stride: 8,
                    displacement: 0.6,
                    displacement_wavelength: 60.0,
                    building_shift: 0.5,
                },
                Preset::Small | Preset::Large => ProxyParams {
                    stride: 2,
                    displacement: 0.05,
                    displacement_wavelength: 60.0,
                    building_shift: 0.05,
                },
            },
            spp_side: match p {
                Preset::Large => 1,
                _ => 4,
            },
            lens: Lens::Pinhole,
        }
    }

    /// Pixel-centre rays in the footprint statistics: every `k`-th row and column (1 but for
    /// `large`, where every pixel would hold 82 million footprints in memory).
    pub fn summary_stride(p: Preset) -> u32 {
        match p {
            Preset::Large => 4,
            _ => 1,
        }
    }
}

/// A generated scene before rendering: the true surface, the proxy mesh and the cameras.
pub struct Synth {
    pub preset: Preset,
    pub seed: u64,
    pub params: Params,
    pub truth: TrueSurface,
    pub proxy: Mesh,
    /// In scene order; view i is named `names[i]`.
    pub views: Vec<Placed>,
    pub names: Vec<String>,
}

/// Build the terrain heightfield.
fn terrain(seed: u64, p: &TerrainParams) -> Heightfield {
    let n = p.cells;
    let cell = 2.0 * p.half_size / n as f64;
    let origin = DVec2::splat(-p.half_size);
    let mut heights = Vec::with_capacity((n + 1) * (n + 1));
    for j in 0..=n {
        for i in 0..=n {
            let (x, y) = (origin.x + i as f64 * cell, origin.y + j as f64 * cell);
            let h: f64 = p
                .octaves
                .iter()
                .enumerate()
                .map(|(k, &[wl, amp])| {
                    2.0 * amp * noise::centred(seed, stream::TERRAIN + k as u64, x, y, wl)
                })
                .sum();
            heights.push(h);
        }
    }
    Heightfield::new(origin, cell, n, heights)
}

/// Lowest and highest terrain under the rectangle `[x0,x1]×[y0,y1]` (sampled at half the cell
/// size, plus corners).
pub fn terrain_range(hf: &Heightfield, x0: f64, x1: f64, y0: f64, y1: f64) -> (f64, f64) {
    let step = 0.5 * hf.cell;
    let nx = ((x1 - x0) / step).ceil() as usize;
    let ny = ((y1 - y0) / step).ceil() as usize;
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for j in 0..=ny {
        for i in 0..=nx {
            let x = (x0 + i as f64 * step).min(x1);
            let y = (y0 + j as f64 * step).min(y1);
            let h = hf.height_at(x, y);
            lo = lo.min(h);
            hi = hi.max(h);
        }
    }
    (lo, hi)
}

fn buildings(seed: u64, p: &BuildingParams, hf: &Heightfield) -> Vec<Building> {
    let r = |k: u64, c: u64| rng::uniform_f64(seed, Purpose::Synth, stream::BUILDINGS, k << 4 | c);
    let mut out: Vec<Building> = Vec::new();
    let mut k = 0u64;
    while out.len() < p.count && k < 10_000 {
        let sx = p.side[0] + (p.side[1] - p.side[0]) * r(k, 0);
        let sy = p.side[0] + (p.side[1] - p.side[0]) * r(k, 1);
        let cx = p.region * (2.0 * r(k, 2) - 1.0);
        let cy = p.region * (2.0 * r(k, 3) - 1.0);
        let (x0, x1, y0, y1) = (cx - 0.5 * sx, cx + 0.5 * sx, cy - 0.5 * sy, cy + 0.5 * sy);
        let g = p.gap;
        let overlaps = out
            .iter()
            .any(|b| x0 < b.hi[0] + g && x1 > b.lo[0] - g && y0 < b.hi[1] + g && y1 > b.lo[1] - g);
        if !overlaps {
            let (lo, hi) = terrain_range(hf, x0, x1, y0, y1);
            let height = p.height[0] + (p.height[1] - p.height[0]) * r(k, 4);
            let wall = [
                0.55 + 0.3 * r(k, 5),
                0.38 + 0.25 * r(k, 6),
                0.28 + 0.2 * r(k, 7),
            ];
            let roof = [
                0.25 + 0.35 * r(k, 8),
                0.25 + 0.3 * r(k, 9),
                0.28 + 0.35 * r(k, 10),
            ];
            out.push(Building {
                lo: [x0, y0, lo - 1.0],
                hi: [x1, y1, hi + height],
                wall_colour: wall,
                roof_colour: roof,
            });
        }
        k += 1;
    }
    out
}

/// Which views are close-ups: `n_close` spread evenly among `n` views (so that the held-out
/// every-7th views include both kinds).
pub fn interleave(n_aerial: usize, n_close: usize) -> Vec<bool> {
    let n = n_aerial + n_close;
    (0..n)
        .map(|i| (i + 1) * n_close / n > i * n_close / n)
        .collect()
}

/// Build geometry and cameras (no rendering).
pub fn build(preset: Preset, seed: u64) -> Synth {
    build_with(preset, Params::preset(preset), seed)
}

/// Build from explicit parameters (tests use reduced ones).
pub fn build_with(preset: Preset, params: Params, seed: u64) -> Synth {
    let hf = terrain(seed, &params.terrain);
    let bs = buildings(seed, &params.buildings, &hf);
    let truth = TrueSurface {
        terrain: hf,
        buildings: bs,
    };
    let proxy = proxy::proxy_mesh(seed, &params.proxy, &truth);
    let close = interleave(params.cameras.n_aerial, params.cameras.n_close);
    let shader = Shader {
        surface: &truth,
        look: &params.look,
        seed,
    };
    let paved = |x: f64, y: f64| shader.paved(x, y);
    let mut views = cameras::place(seed, &params.cameras, &truth, &close, &paved);
    for v in &mut views {
        v.camera.distortion = params.lens.distortion();
    }
    let names = (0..views.len()).map(|i| format!("{i:04}.png")).collect();
    Synth {
        preset,
        seed,
        params,
        truth,
        proxy,
        views,
        names,
    }
}

impl Synth {
    pub fn shader(&self) -> Shader<'_> {
        Shader {
            surface: &self.truth,
            look: &self.params.look,
            seed: self.seed,
        }
    }

    /// Render every view's ground truth (views in order, pixels in parallel).
    pub fn render(&self) -> Vec<Image> {
        let sh = self.shader();
        self.views
            .iter()
            .map(|v| render::render(&sh, &v.camera, self.params.spp_side))
            .collect()
    }

    /// Footprint statistics and coverage.
    pub fn summary(&self) -> Summary {
        let mut aerial = Vec::new();
        let mut close = Vec::new();
        let mut min_hit = 1.0f64;
        for v in &self.views {
            let stride = Params::summary_stride(self.preset);
            let (fp, frac) = render::footprints_strided(&self.truth, &v.camera, stride);
            min_hit = min_hit.min(frac);
            match v.kind {
                ViewKind::Aerial => aerial.extend(fp),
                ViewKind::Close => close.extend(fp),
            }
        }
        let a = Stats::of(&mut aerial);
        let c = Stats::of(&mut close);
        Summary {
            views: self.views.len(),
            aerial_views: self
                .views
                .iter()
                .filter(|v| v.kind == ViewKind::Aerial)
                .count(),
            close_views: self
                .views
                .iter()
                .filter(|v| v.kind == ViewKind::Close)
                .count(),
            true_triangles: 2 * self.truth.terrain.n * self.truth.terrain.n
                + 10 * self.truth.buildings.len(),
            proxy_triangles: self.proxy.triangles.len(),
            ratio_median: a.median / c.median,
            ratio_min_over_max: a.min / c.max,
            footprint_aerial: a,
            footprint_close: c,
            min_hit_fraction: min_hit,
        }
    }
}

/// Min / median / max of a set of footprints (m).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Stats {
    pub min: f64,
    pub median: f64,
    pub max: f64,
}

impl Stats {
    fn of(v: &mut [f64]) -> Stats {
        if v.is_empty() {
            return Stats {
                min: f64::NAN,
                median: f64::NAN,
                max: f64::NAN,
            };
        }
        v.sort_by(f64::total_cmp);
        Stats {
            min: v[0],
            median: v[v.len() / 2],
            max: v[v.len() - 1],
        }
    }
}

/// What `xscale synth` prints and `synth.toml` records.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Summary {
    pub views: usize,
    pub aerial_views: usize,
    pub close_views: usize,
    pub true_triangles: usize,
    pub proxy_triangles: usize,
    /// Pixel footprints (pixel-centre rays that hit, m; see `render.rs` for the convention).
    pub footprint_aerial: Stats,
    pub footprint_close: Stats,
    /// median(aerial) / median(close-up).
    pub ratio_median: f64,
    /// min(aerial) / max(close-up): the most pessimistic pairing.
    pub ratio_min_over_max: f64,
    /// Smallest fraction of pixel-centre rays that hit the surface in any view.
    pub min_hit_fraction: f64,
}

impl std::fmt::Display for Summary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (a, c) = (&self.footprint_aerial, &self.footprint_close);
        writeln!(
            f,
            "views: {} ({} aerial, {} close-up)",
            self.views, self.aerial_views, self.close_views
        )?;
        writeln!(
            f,
            "triangles: true {} / proxy {}",
            self.true_triangles, self.proxy_triangles
        )?;
        writeln!(
            f,
            "pixel footprint aerial:   min {:.4} m, median {:.4} m, max {:.4} m",
            a.min, a.median, a.max
        )?;
        writeln!(
            f,
            "pixel footprint close-up: min {:.4} m, median {:.4} m, max {:.4} m",
            c.min, c.median, c.max
        )?;
        writeln!(
            f,
            "footprint ratio aerial/close-up: {:.1}× (medians), {:.1}× (min aerial / max close-up)",
            self.ratio_median, self.ratio_min_over_max
        )?;
        write!(
            f,
            "surface coverage: ≥ {:.1}% of pixels in every view",
            100.0 * self.min_hit_fraction
        )
    }
}

/// Convenience for tests: the surface point hit by a ray, if any.
pub fn surface_point(s: &TrueSurface, o: DVec3, d: DVec3) -> Option<DVec3> {
    s.trace(o, d, 0.0, f64::INFINITY).map(|h| h.pos)
}

/// Build, render and write scene (`preset`, `seed`) into `dir` (`truth.ply` too with
/// `write_truth`); `progress(i, n)` after view i of n is written (an error from it stops there).
pub fn generate(
    preset: Preset,
    seed: u64,
    lens: Lens,
    dir: &Path,
    write_truth: bool,
    progress: &mut dyn FnMut(usize, usize) -> anyhow::Result<()>,
) -> anyhow::Result<Summary> {
    let s = build_with(
        preset,
        Params {
            lens,
            ..Params::preset(preset)
        },
        seed,
    );
    let summary = s.summary();
    let n = s.views.len();
    let sh = s.shader();
    let spp = s.params.spp_side;
    // One view rendered and written at a time (the `large` preset's 104 views would hold 1 GB).
    output::write_with(
        &s,
        &mut |i| render::render(&sh, &s.views[i].camera, spp),
        &summary,
        dir,
        write_truth,
        &mut |i| progress(i, n),
    )?;
    Ok(summary)
}
