//! A packet of rays traced together: [`Packet`] (structure of arrays, up to [`MAX_LANES`] lanes).
//! Shared by the traversal (`bvh.rs`) and the lane ray–triangle test (`triangle.rs`), which
//! both depend on it and not on each other's types.

/// Most lanes a packet has.
pub const MAX_LANES: usize = 16;

/// Up to [`MAX_LANES`] rays in the local frame (f32) traced together, structure of arrays.
/// Inactive lanes are ignored. Which rays share a packet never changes their results, only the
/// speed.
#[derive(Clone, Copy, Debug, Default)]
pub struct Packet {
    /// `[axis][lane]`.
    pub origin: [[f32; MAX_LANES]; 3],
    /// `[axis][lane]`.
    pub dir: [[f32; MAX_LANES]; 3],
    /// Bit i set: lane i is a ray.
    pub active: u32,
}

impl Packet {
    /// Make lane `i` the ray `(origin, dir)`.
    #[inline]
    pub fn set(&mut self, i: usize, origin: [f32; 3], dir: [f32; 3]) {
        for a in 0..3 {
            self.origin[a][i] = origin[a];
            self.dir[a][i] = dir[a];
        }
        self.active |= 1 << i;
    }

    #[inline]
    pub fn origin(&self, i: usize) -> [f32; 3] {
        [self.origin[0][i], self.origin[1][i], self.origin[2][i]]
    }

    #[inline]
    pub fn dir(&self, i: usize) -> [f32; 3] {
        [self.dir[0][i], self.dir[1][i], self.dir[2][i]]
    }

    /// Copy lane `src` of `from` into lane `dst` (the active mask is unchanged).
    #[inline]
    pub(super) fn copy_lane_from(&mut self, dst: usize, from: &Packet, src: usize) {
        for a in 0..3 {
            self.origin[a][dst] = from.origin[a][src];
            self.dir[a][dst] = from.dir[a][src];
        }
    }
}
