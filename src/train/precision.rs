//! The training step with the model evaluated in f64 (`TrainState::step_f64`): forward and
//! backward run in f64 (the model is generic over its scalar, SPEC §4.2 "when the whole model is
//! instantiated in f64"), the gradient is rounded once to f32 and Adam updates the f32
//! parameters exactly as in [`TrainState::step`]. So the checkpoint format, Adam and its state
//! are unchanged; only the arithmetic of the model differs. Used by `xscale bench-quality` to
//! weigh f32 against f64 arithmetic (error against time).
//!
//! The f64 copy of the parameters is kept in step with the f32 ones: after each Adam step only
//! the grid entries that step touched and the other (small) tensors are converted again, so a
//! step costs what the batch touched, not the table size.

use crate::model::batch::Batch;
use crate::model::params::{Grads, Group};
use crate::train::config::Arithmetic;
use crate::train::state::{batch_mse, StepStats, TrainState};
use anyhow::{ensure, Result};
use std::time::Instant;

/// The f64 side of [`TrainState::step_f64`]: the parameters converted to f64 and the f64
/// gradient buffers. Build it from the state it will step ([`F64Step::new`]).
pub struct F64Step {
    params: Vec<f64>,
    grads: Grads<f64>,
}

impl F64Step {
    /// The f64 side of `state` if its run trains in f64 (`[train] arithmetic = "f64"`).
    pub fn for_config(state: &TrainState) -> Option<F64Step> {
        (state.cfg.train.arithmetic == Arithmetic::F64).then(|| F64Step::new(state))
    }

    /// The f64 copy of `state`'s parameters, zero f64 gradients.
    pub fn new(state: &TrainState) -> F64Step {
        let mut grads = Grads::new(&state.ckpt.model.layout);
        grads.inputs = false;
        F64Step {
            params: state.ckpt.params.iter().map(|&v| v as f64).collect(),
            grads,
        }
    }

    /// The f64 parameters (each equal to the f32 parameter it mirrors).
    pub fn params(&self) -> &[f64] {
        &self.params
    }
}

/// For each tensor of the layout: its grid features per entry and touched list, or `None` for a
/// dense tensor.
fn entries_of<'a>(
    t: &crate::model::params::TensorSpec,
    touched: [&'a [u32]; 3],
    fh: usize,
    fd: usize,
) -> Option<(&'a [u32], usize)> {
    match t.group {
        Group::GridH => Some((touched[0], fh)),
        Group::GridD => Some((touched[1], fd)),
        Group::Vertex => Some((touched[2], t.shape[1])),
        _ => None,
    }
}

fn touched<R>(g: &Grads<R>) -> [&[u32]; 3] {
    [
        &g.touched_h.entries,
        &g.touched_d.entries,
        &g.touched_v.entries,
    ]
}

impl TrainState {
    /// One step in the run's arithmetic: [`TrainState::step_f64`] with `f64s`, else
    /// [`TrainState::step`].
    pub fn step_in(
        &mut self,
        batch: &Batch,
        grads: &mut Grads<f32>,
        f64s: Option<&mut F64Step>,
    ) -> Result<StepStats> {
        match f64s {
            Some(f) => self.step_f64(batch, grads, f),
            None => self.step(batch, grads),
        }
    }

    /// One optimisation step on `batch` with the model in f64 (module doc). `grads` (f32) must be
    /// zero on entry and is zero on exit, as for [`TrainState::step`]; `f64s` must mirror this
    /// state's parameters (built by [`F64Step::new`] from it and stepped only through here).
    pub fn step_f64(
        &mut self,
        batch: &Batch,
        grads: &mut Grads<f32>,
        f64s: &mut F64Step,
    ) -> Result<StepStats> {
        ensure!(
            f64s.params.len() == self.ckpt.params.len(),
            "step_f64: the f64 parameters ({}) do not mirror this state ({})",
            f64s.params.len(),
            self.ckpt.params.len()
        );
        let model = &self.ckpt.model;
        let (fh, fd) = model.grid_features();
        let t0 = Instant::now();
        let fwd = model.forward(&f64s.params, batch)?;
        let t1 = Instant::now();
        model.backward(&f64s.params, batch, &fwd, &mut f64s.grads);
        // The gradient rounded once to f32 (touched grid entries, every other tensor), the f64
        // gradient zeroed as it is read.
        let Grads {
            params: g64_all,
            touched_h,
            touched_d,
            touched_v,
            ..
        } = &mut f64s.grads;
        let lists = [
            &touched_h.entries[..],
            &touched_d.entries[..],
            &touched_v.entries[..],
        ];
        for t in &model.layout.tensors {
            let r = t.range();
            let (g32, g64) = (&mut grads.params[r.clone()], &mut g64_all[r]);
            match entries_of(t, lists, fh, fd) {
                Some((entries, f)) => {
                    for &e in entries {
                        let b = e as usize * f;
                        for (d, s) in g32[b..b + f].iter_mut().zip(&mut g64[b..b + f]) {
                            *d = *s as f32;
                            *s = 0.0;
                        }
                    }
                }
                None => {
                    for (d, s) in g32.iter_mut().zip(g64.iter_mut()) {
                        *d = *s as f32;
                        *s = 0.0;
                    }
                }
            }
        }
        for (d, s) in [
            (&mut grads.touched_h, &mut f64s.grads.touched_h),
            (&mut grads.touched_d, &mut f64s.grads.touched_d),
            (&mut grads.touched_v, &mut f64s.grads.touched_v),
        ] {
            std::mem::swap(&mut d.entries, &mut s.entries);
            s.entries.clear();
        }
        let t2 = Instant::now();
        let mse = batch_mse(&fwd, batch);
        self.apply_adam(grads);
        // The f64 copy follows what Adam changed.
        let model = &self.ckpt.model;
        for t in &model.layout.tensors {
            let r = t.range();
            let (p32, p64) = (&self.ckpt.params[r.clone()], &mut f64s.params[r]);
            match entries_of(t, touched(grads), fh, fd) {
                Some((entries, f)) => {
                    for &e in entries {
                        let b = e as usize * f;
                        for (d, s) in p64[b..b + f].iter_mut().zip(&p32[b..b + f]) {
                            *d = *s as f64;
                        }
                    }
                }
                None => {
                    for (d, s) in p64.iter_mut().zip(p32) {
                        *d = *s as f64;
                    }
                }
            }
        }
        Ok(self.finish_step(grads, fwd.loss, mse, fwd.points.len(), [t0, t1, t2]))
    }
}
