//! The model's parameters as ONE flat buffer with a named layout (SPEC §6 names), and gradients
//! in the same layout.
//!
//! Layout order (each group contiguous, so an optimiser can take one slice per group):
//! `grid_h.table` [entries, F] (or, with the vertex featurization, `vertex.features` [V, Z]) ·
//! `grid_d.table` [entries, F] · `deform.layers.{i}.weight`
//! `[out, in]` (+ `.bias` `[out]`) · `shader.layers.{i}.weight` (+ `.bias`) · `appearance.codes`
//! [views, A]. Parts that are switched off have no tensors.
//!
//! Gradients ([`Grads`]) hold ∂L/∂params in the same layout plus ∂L/∂batch.positions and
//! ∂L/∂batch.dirs; every backward accumulates, and zeroing is one explicit call ([`Grads::zero`],
//! or [`Grads::zero_sparse`] which clears only the grid entries recorded as touched).

use crate::model::hashgrid::Touched;
use std::ops::Range;

/// Parameter groups: each has its own learning rate in the optimiser (SPEC §4.8).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Group {
    GridH,
    GridD,
    Deform,
    Shader,
    Appearance,
    /// The vertex-feature table (the Fig. 2b baseline, `src/model/vertex.rs`).
    Vertex,
}

impl Group {
    pub const ALL: [Group; 6] = [
        Group::GridH,
        Group::GridD,
        Group::Deform,
        Group::Shader,
        Group::Appearance,
        Group::Vertex,
    ];
    pub fn name(self) -> &'static str {
        match self {
            Group::GridH => "grid_h",
            Group::GridD => "grid_d",
            Group::Deform => "deform",
            Group::Shader => "shader",
            Group::Appearance => "appearance",
            Group::Vertex => "vertex",
        }
    }
    /// Grid tables, the vertex table and appearance codes are "sparse" groups: Adam skips their
    /// entries whose gradient is exactly zero (SPEC §4.8).
    pub fn is_sparse(self) -> bool {
        matches!(
            self,
            Group::GridH | Group::GridD | Group::Appearance | Group::Vertex
        )
    }
}

/// One named tensor inside the flat buffer.
#[derive(Clone, Debug, PartialEq)]
pub struct TensorSpec {
    pub name: String,
    pub shape: Vec<usize>,
    pub offset: usize,
    pub len: usize,
    pub group: Group,
}

impl TensorSpec {
    pub fn range(&self) -> Range<usize> {
        self.offset..self.offset + self.len
    }
}

/// The named layout of the flat parameter buffer.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct ParamLayout {
    pub tensors: Vec<TensorSpec>,
    pub total: usize,
}

impl ParamLayout {
    /// Append a tensor at the end (groups must be pushed contiguously).
    pub fn push(&mut self, name: &str, shape: &[usize], group: Group) -> Range<usize> {
        let len = shape.iter().product();
        if let Some(last) = self.tensors.last() {
            assert!(
                last.group == group || self.group_range(group).is_none(),
                "group {group:?} must be contiguous"
            );
        }
        let offset = self.total;
        self.tensors.push(TensorSpec {
            name: name.to_string(),
            shape: shape.to_vec(),
            offset,
            len,
            group,
        });
        self.total += len;
        offset..offset + len
    }

    /// `(name, shape)` of every tensor in layout order (what `train::adam::AdamState::new`
    /// takes).
    pub fn name_shapes(&self) -> Vec<(String, Vec<usize>)> {
        self.tensors
            .iter()
            .map(|t| (t.name.clone(), t.shape.clone()))
            .collect()
    }

    pub fn get(&self, name: &str) -> Option<&TensorSpec> {
        self.tensors.iter().find(|t| t.name == name)
    }

    /// Range of a named tensor; panics with the name if absent (a programming error).
    pub fn range(&self, name: &str) -> Range<usize> {
        self.get(name)
            .unwrap_or_else(|| panic!("no parameter tensor named {name:?}"))
            .range()
    }

    /// The contiguous range a group occupies, `None` if the group has no tensors.
    pub fn group_range(&self, group: Group) -> Option<Range<usize>> {
        let mut it = self.tensors.iter().filter(|t| t.group == group);
        let first = it.next()?;
        let end = it
            .next_back()
            .map_or(first.offset + first.len, |t| t.offset + t.len);
        Some(first.offset..end)
    }

    /// A named view into a buffer in this layout (parameters, gradients, Adam moments…).
    pub fn view<'a, T>(&self, data: &'a [T], name: &str) -> &'a [T] {
        &data[self.range(name)]
    }

    pub fn view_mut<'a, T>(&self, data: &'a mut [T], name: &str) -> &'a mut [T] {
        &mut data[self.range(name)]
    }

    /// Every tensor of a group with its slice.
    pub fn group_views<'a, 'b, T>(
        &'a self,
        data: &'b [T],
        group: Group,
    ) -> impl Iterator<Item = (&'a TensorSpec, &'b [T])> + use<'a, 'b, T> {
        self.tensors
            .iter()
            .filter(move |t| t.group == group)
            .map(move |t| (t, &data[t.range()]))
    }
}

/// Gradients of one loss evaluation: ∂L/∂params in the layout, plus the input gradients.
#[derive(Clone, Debug)]
pub struct Grads<R> {
    /// `[layout.total]`.
    pub params: Vec<R>,
    /// ∂L/∂batch.positions `[N, S, 3]` (zero rows for invalid sub-samples).
    pub positions: Vec<R>,
    /// ∂L/∂batch.dirs `[N, 3]`.
    pub dirs: Vec<R>,
    /// Compute `positions` and `dirs` (default). Training turns this off: positions and
    /// directions are fixed data there, and the grids' position backward is their most
    /// expensive pass. Parameter gradients are identical either way.
    pub inputs: bool,
    /// Grid H entries that received gradient since the last zeroing (unique, sorted).
    pub touched_h: Touched,
    /// The same for grid D.
    pub touched_d: Touched,
    /// Rows of the vertex table (vertex featurization) that received gradient.
    pub touched_v: Touched,
    /// With `inputs`: the position gradient goes through only the grid levels (of H and D)
    /// whose scale is at most this many cells per unit (`None`: every level, the exact
    /// gradient). The mesh refinement's coarse-to-fine schedule (`refine/refiner.rs`); parameter
    /// gradients are unaffected.
    pub position_max_scale: Option<f32>,
    /// Scratch of the backward pass, kept to be reused: the chunks write their rows of
    /// ∂L/∂F_H `[v, L·F]` and ∂L/∂F_D `[v, L_D·F_D]` here, in batch order, for the grids'
    /// table backward (no meaning between calls).
    pub(crate) rows_h: Vec<R>,
    pub(crate) rows_d: Vec<R>,
}

impl<R: Copy + Default + Send + Sync> Grads<R> {
    /// Zero gradients for a layout (input gradients sized on the first backward).
    pub fn new(layout: &ParamLayout) -> Grads<R> {
        Grads {
            params: crate::memhint::filled(layout.total, R::default()),
            positions: Vec::new(),
            dirs: Vec::new(),
            inputs: true,
            touched_h: Touched::default(),
            touched_d: Touched::default(),
            touched_v: Touched::default(),
            position_max_scale: None,
            rows_h: Vec::new(),
            rows_d: Vec::new(),
        }
    }

    /// Zero everything (dense).
    pub fn zero(&mut self) {
        self.params.fill(R::default());
        self.positions.fill(R::default());
        self.dirs.fill(R::default());
        self.touched_h.entries.clear();
        self.touched_d.entries.clear();
        self.touched_v.entries.clear();
    }

    /// Zero only what a backward can have written: the touched entries of each grid table
    /// (`features` floats per entry), the touched rows of the vertex table (its shape's second
    /// axis floats per row) and every other tensor densely. Costs what the batch touched, not
    /// the table size.
    pub fn zero_sparse(&mut self, layout: &ParamLayout, features_h: usize, features_d: usize) {
        for t in &layout.tensors {
            let (touched, f) = match t.group {
                Group::GridH => (&mut self.touched_h, features_h),
                Group::GridD => (&mut self.touched_d, features_d),
                Group::Vertex => (&mut self.touched_v, t.shape[1]),
                _ => {
                    self.params[t.range()].fill(R::default());
                    continue;
                }
            };
            let table = &mut self.params[t.range()];
            for &e in &touched.entries {
                let e = e as usize * f;
                table[e..e + f].fill(R::default());
            }
            touched.entries.clear();
        }
        self.positions.fill(R::default());
        self.dirs.fill(R::default());
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_views_and_groups() {
        let mut l = ParamLayout::default();
        l.push("grid_h.table", &[10, 2], Group::GridH);
        l.push("shader.layers.0.weight", &[3, 4], Group::Shader);
        l.push("shader.layers.0.bias", &[3], Group::Shader);
        l.push("appearance.codes", &[5, 2], Group::Appearance);
        assert_eq!(l.total, 20 + 12 + 3 + 10);
        assert_eq!(l.group_range(Group::Shader), Some(20..35));
        assert_eq!(l.group_range(Group::GridD), None);
        let data: Vec<u32> = (0..l.total as u32).collect();
        assert_eq!(l.view(&data, "shader.layers.0.bias"), &[32, 33, 34]);
        assert_eq!(l.group_views(&data, Group::Shader).count(), 2);
    }

    #[test]
    fn sparse_zero_clears_touched_only() {
        let mut l = ParamLayout::default();
        l.push("grid_h.table", &[4, 2], Group::GridH);
        l.push("shader.layers.0.weight", &[2, 2], Group::Shader);
        let mut g = Grads::<f32>::new(&l);
        g.params.fill(1.0);
        g.touched_h.entries = vec![1, 3];
        g.zero_sparse(&l, 2, 2);
        assert_eq!(&g.params[..8], &[1.0, 1.0, 0.0, 0.0, 1.0, 1.0, 0.0, 0.0]);
        assert!(g.params[8..].iter().all(|&v| v == 0.0));
        assert!(g.touched_h.entries.is_empty());
    }
}
