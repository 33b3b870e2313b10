//! Model configuration and presets (SPEC §4, §9). Serialised as TOML into every checkpoint's
//! `config` metadata; a reader (the PyTorch reference, a backend) takes the numbers from here and
//! the per-level scale table from the checkpoint's `grid_*.scales` tensor.

pub use crate::model::refine::RefineConfig;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Interpolation {
    #[default]
    Linear,
    Smoothstep,
}

/// How grid positions are computed (SPEC §4.2 "Precision modes").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum PositionMode {
    /// `p = fma(scale as f64, x_n, 0.5)` in f64; only the cell fraction goes to the model's float.
    #[default]
    F64,
    /// `x_n` rounded to f32, `p = f32::mul_add(scale, x_n, 0.5)`: bit-compatible with tiny-cuda-nn fp32.
    Tcnn,
}

/// One multi-resolution hash grid (SPEC §4.2).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridConfig {
    /// Number of levels L (after dropping levels finer than any footprint, SPEC §8).
    pub levels: u32,
    /// Features per level F ∈ {1, 2, 4, 8}.
    pub features: u32,
    /// log2 of the maximum entries per level, T (with `log2_table_sizes`: their largest).
    pub log2_table_size: u32,
    /// log2 of the maximum entries of each level, `T_l` (a documented extension of tiny-cuda-nn,
    /// which has one `T` for all levels; SPEC §4.2): chosen by `log2_table_size = "auto"` from the
    /// surface cells the training rays reach (`train/setup.rs` `resolve_table_sizes`). Absent: every
    /// level has `T`, as in tiny-cuda-nn (the `tiny` and `paper` presets, an explicit integer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log2_table_sizes: Option<Vec<u32>>,
    /// N0.
    pub base_resolution: f32,
    /// b; `scale_l = exp2(l * log2(b)) * N0 - 1` with log2(b) in f32.
    pub per_level_scale: f64,
    pub interpolation: Interpolation,
    /// The finest level's resolution `N_max` that `per_level_scale` was derived from
    /// (`(N_max / N0)^(1/(L-1))`): given in a config file, or chosen by `level_range = "auto"`.
    /// Informational once resolved: `per_level_scale` (and the saved scale table) is what
    /// defines the grid. Absent when the preset's scale is used.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finest_resolution: Option<f64>,
}

impl GridConfig {
    /// `T_l`: log2 of the maximum entries of level `l` (`log2_table_sizes[l]`, else `T`).
    pub fn log2_table_size_of(&self, l: usize) -> u32 {
        self.log2_table_sizes
            .as_ref()
            .and_then(|v| v.get(l).copied())
            .unwrap_or(self.log2_table_size)
    }
}

/// The manifold deformation ξ (SPEC §4.4, Eq. 5).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeformConfig {
    pub enabled: bool,
    pub grid: GridConfig,
    /// Width of ξ's single hidden ReLU layer.
    pub hidden: u32,
}

/// A ReLU MLP (SPEC §4.6).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShaderConfig {
    pub hidden_layers: u32,
    pub width: u32,
    pub bias: bool,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum LossKind {
    #[default]
    L1,
    L2,
    SmoothL1,
}

/// What is queried at each surface sub-sample before pooling (the paper's Fig. 2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Featurization {
    /// The hash featurized manifold: grid H at the hit position (Fig. 2d, Eq. 2).
    #[default]
    Hash,
    /// The 3D-surface-based baseline (Fig. 2b): one learnable `vertex_features`-vector per mesh
    /// vertex, interpolated with the hit's barycentrics (`src/model/vertex.rs`). Grid H, grid D
    /// and ξ are not used (deformation must be off).
    Vertex,
}

impl Featurization {
    pub fn is_hash(&self) -> bool {
        *self == Featurization::Hash
    }
}

/// How a sub-sample's grid-H levels are weighted (SPEC §4.10).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum LevelWeight {
    /// Every level at weight 1: Eqs. 2 and 4 as the paper writes them.
    #[default]
    None,
    /// Level l of a sub-sample is scaled by `w(r)`, `r = footprint · scale_l` (the pixel's
    /// footprint in cells of level l): 1 for r ≤ 1, 0 for r ≥ 4, a smoothstep in log2(r) between
    /// (`src/model/level_weight.rs`). A far pixel neither reads nor writes levels much finer than
    /// itself; levels at weight 0 are not evaluated.
    Footprint,
}

impl LevelWeight {
    pub fn is_none(&self) -> bool {
        *self == LevelWeight::None
    }
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

fn is_zero_f64(v: &f64) -> bool {
    *v == 0.0
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    pub grid_h: GridConfig,
    pub deform: DeformConfig,
    pub shader: ShaderConfig,
    /// Appearance code size A (0 disables).
    pub appearance_dim: u32,
    /// Rows of the appearance table: the number of training views (set when a model is
    /// initialised for a scene).
    pub appearance_views: u32,
    /// Multisampling factor γ: γ² rays per pixel (Eq. 4).
    pub gamma: u32,
    pub positions: PositionMode,
    pub loss: LossKind,
    /// δ of smooth-L1.
    pub smooth_l1_delta: f64,
    /// λ of the structural term on patch batches (SPEC §4.7, `model/ssim.rs`): the loss is
    /// `(1−λ)·ρ + λ·(1 − SSIM)` when a batch holds patches (`[train] patch`), ρ alone when it
    /// does not. Absent when 0 (the `tiny` and `paper` presets, configs written before it).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub ssim_weight: f64,
    /// `hash` (default) or `vertex` (the Fig. 2b baseline). Absent from a hash model's TOML, so
    /// hash configs and checkpoints are unchanged by the switch's existence.
    #[serde(default, skip_serializing_if = "Featurization::is_hash")]
    pub featurization: Featurization,
    /// Z: features per mesh vertex (vertex featurization only; the shader input is
    /// `[Z, SH(d), code]`).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub vertex_features: u32,
    /// Rows of the vertex table: the mesh's vertex count (set when a vertex model is initialised
    /// for a scene, like `appearance_views`).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub vertex_count: u32,
    /// Footprint-aware weighting of grid H's levels (SPEC §4.10; beyond the paper). Always
    /// written (`"none"` too): the `cpu` preset has it on, so a `RUN/config.toml` without the key,
    /// laid over its preset as a `--config`, would turn it on. Absent from configs written before
    /// it existed (= none, as they were trained).
    #[serde(default)]
    pub level_weight: LevelWeight,
    /// Joint refinement of the mesh through the hit point (`[model.refine]`, beyond the paper;
    /// `model/refine.rs`; its defaults are the photo-consistency refinement). Absent from configs
    /// that keep the default (off).
    #[serde(default, skip_serializing_if = "RefineConfig::is_default")]
    pub refine: RefineConfig,
}

/// `(finest / base)^(1/(levels-1))`, the per-level scale that reaches `finest` at the last level.
pub fn per_level_scale_for(base: f64, finest: f64, levels: u32) -> f64 {
    (finest / base).powf(1.0 / (levels as f64 - 1.0))
}

impl ModelConfig {
    /// `tiny`: for the oracle in CI and unit tests (SPEC §9).
    pub fn tiny() -> ModelConfig {
        ModelConfig {
            grid_h: GridConfig {
                levels: 4,
                features: 2,
                log2_table_size: 12,
                base_resolution: 4.0,
                per_level_scale: 2.0,
                interpolation: Interpolation::Linear,
                finest_resolution: None,
                log2_table_sizes: None,
            },
            deform: DeformConfig {
                enabled: true,
                grid: GridConfig {
                    levels: 2,
                    features: 2,
                    log2_table_size: 10,
                    base_resolution: 4.0,
                    per_level_scale: 2.0,
                    interpolation: Interpolation::Linear,
                    finest_resolution: None,
                    log2_table_sizes: None,
                },
                hidden: 8,
            },
            shader: ShaderConfig {
                hidden_layers: 1,
                width: 16,
                bias: false,
            },
            appearance_dim: 2,
            appearance_views: 0,
            gamma: 2,
            positions: PositionMode::F64,
            loss: LossKind::L1,
            smooth_l1_delta: 0.01,
            ssim_weight: 0.0,
            featurization: Featurization::Hash,
            vertex_features: 0,
            vertex_count: 0,
            level_weight: LevelWeight::None,
            refine: RefineConfig::default(),
        }
    }

    /// `cpu` (default): small scenes on a laptop (SPEC §9).
    pub fn cpu() -> ModelConfig {
        ModelConfig {
            grid_h: GridConfig {
                levels: 16,
                features: 2,
                log2_table_size: 19,
                base_resolution: 16.0,
                per_level_scale: per_level_scale_for(16.0, 2048.0, 16),
                interpolation: Interpolation::Linear,
                finest_resolution: None,
                log2_table_sizes: None,
            },
            deform: DeformConfig {
                enabled: true,
                // The spacing of 8 levels from 16 to 512, the 5 coarsest of them (finest
                // res_4 = 116): the three finer ones held most of grid D's stepped rows
                // and bought no held-out PSNR on tiny, small or cross, a little SSIM on the
                // real fox capture (SPEC §9, docs/changelog.md "Grid D's levels").
                grid: GridConfig {
                    levels: 5,
                    features: 2,
                    log2_table_size: 17,
                    base_resolution: 16.0,
                    per_level_scale: per_level_scale_for(16.0, 512.0, 8),
                    interpolation: Interpolation::Linear,
                    finest_resolution: None,
                    log2_table_sizes: None,
                },
                hidden: 32,
            },
            shader: ShaderConfig {
                hidden_layers: 2,
                width: 64,
                bias: false,
            },
            appearance_dim: 4,
            appearance_views: 0,
            gamma: 2,
            positions: PositionMode::F64,
            loss: LossKind::L1,
            smooth_l1_delta: 0.01,
            ssim_weight: 0.0,
            featurization: Featurization::Hash,
            vertex_features: 0,
            vertex_count: 0,
            // Measured better on synth small (+0.7 dB masked PSNR, 18% faster per step; SPEC §4.10).
            level_weight: LevelWeight::Footprint,
            refine: RefineConfig::default(),
        }
    }

    /// `paper`: the official code's grid (SPEC §9).
    pub fn paper() -> ModelConfig {
        let mut c = ModelConfig::cpu();
        c.level_weight = LevelWeight::None; // the paper's Eqs. 2 and 4
        c.grid_h = GridConfig {
            levels: 16,
            features: 8,
            log2_table_size: 22,
            base_resolution: 16.0,
            per_level_scale: 1.4768261459394993,
            interpolation: Interpolation::Smoothstep,
            finest_resolution: None,
            log2_table_sizes: None,
        };
        c.deform.grid.interpolation = Interpolation::Smoothstep;
        c.deform.grid.levels = 8; // finest res_7 = 512 (`cpu` keeps the 5 coarsest)
        c
    }

    pub fn preset(name: &str) -> anyhow::Result<ModelConfig> {
        match name {
            "tiny" => Ok(ModelConfig::tiny()),
            "cpu" => Ok(ModelConfig::cpu()),
            "paper" => Ok(ModelConfig::paper()),
            _ => anyhow::bail!("unknown preset {name:?}: expected one of tiny, cpu, paper"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn featurization_switch_is_absent_from_hash_configs() {
        let c = ModelConfig::cpu();
        let s = toml::to_string(&c).unwrap();
        assert!(
            !s.contains("featurization") && !s.contains("vertex_"),
            "{s}"
        );
        let mut v = c.clone();
        v.featurization = Featurization::Vertex;
        v.vertex_features = 12;
        v.vertex_count = 99;
        let s = toml::to_string(&v).unwrap();
        assert!(s.contains("featurization = \"vertex\""), "{s}");
        assert_eq!(toml::from_str::<ModelConfig>(&s).unwrap(), v);
    }

    #[test]
    fn toml_roundtrip() {
        for name in ["tiny", "cpu", "paper"] {
            let c = ModelConfig::preset(name).unwrap();
            let s = toml::to_string(&c).unwrap();
            let back: ModelConfig = toml::from_str(&s).unwrap();
            assert_eq!(c, back, "{s}");
        }
    }
}
