//! The ToF renderer: per-pixel phasors of a camera that looks through planar mirrors into an
//! indoor world of vertical walls, boxes, a floor and a ceiling. Pure Rust, no Python.
//!
//! Frames and units: metres, radians. The world frame has x, y on the floor and z up; the floor
//! is z = 0 and the ceiling z = `ceiling_height`. Sub-ray directions and mirrors are given in
//! the camera frame (omnitof.camera's: x right, y down, z along the optical axis); a robot pose
//! (x, y, θ) and the fixed mount robot_T_camera place the camera in the world:
//! world_T_camera = world_T_robot(x, y, θ) · robot_T_camera.
//!
//! Light model (the light source is coaxial with the camera, so light leaves and returns along
//! the same path, and the phase follows the round trip 2r, r the one-way path length from the
//! camera centre through the mirror to the surface):
//!
//! - a diffuse return adds the phasor  g2 · albedo · cos(incidence) / r² · e^{i·4π f r / c},
//!   scaled by `amplitude_at_1m`, where g2 is the product over the path of the squared
//!   reflectivities and transmittances met on the way (each is passed twice);
//! - each pixel's phasor is the mean over its sub-rays, so pixels that straddle a depth edge or a
//!   mirror edge mix two distances ("flying" pixels) by themselves;
//! - besides the phasor each pixel reports Σ|p| (the DC part of the modulated light, which the
//!   noise model needs for mixed pixels) and Σ g1 · albedo, g1 the one-way product: how bright the
//!   seen surfaces are under uniform ambient light (scaled to an offset on the Python side).
//!
//! Materials: matte (diffuse albedo); metal (weak diffuse part, and a mirrored fraction that is
//! followed as a new ray); glass (weak diffuse part, a weak mirrored fraction, and a transmitted
//! fraction that continues straight on); grid (a coarse lattice of bars: rays that meet a bar
//! return diffusely, the others pass through the holes). Specular bounces are limited by
//! `max_bounces`, pass-throughs (glass, grid holes) by `MAX_PASSES`.
//!
//! Acceleration: walls and boxes are binned into a uniform 2D grid over the floor plan (each
//! cell lists the primitives whose footprint touches it); a ray walks the cells under its
//! horizontal projection with `raycast::traverse` (Amanatides & Woo) and stops at the first cell
//! that ends beyond the nearest hit found so far. A primitive that lies in several cells is
//! tested once per ray (`Mailbox`). Floor and ceiling are planes tested before the walk; they
//! bound its length. With the LEDs on, each sub-ray's first surface tests only the light sources
//! that can light some point of that sub-ray (`light_masks`, worked out once per rig).
//!
//! Determinism: nothing here is random (sub-ray jitter is chosen by the caller, the grid's bars
//! are a fixed pattern in space), and each pixel sums its sub-rays in a fixed order, so the
//! output is the same bit for bit for any number of threads.

use rayon::prelude::*;

use crate::light::{candidate_masks, pose_hash, uniforms_of_pose, Illumination, PoseLight, SubRayLight};
use crate::raycast::{floor_i32, traverse};

/// Speed of light in vacuum, m/s (exact by definition of the metre).
pub const SPEED_OF_LIGHT: f64 = 299_792_458.0;
/// Rays start this far (metres) beyond their origin, so a ray leaving a surface does not hit it.
pub(crate) const T_MIN: f64 = 1e-6;
/// Limit on pass-throughs (glass, grid holes) along one path: bounds the work per ray.
pub const MAX_PASSES: u32 = 6;
/// Light paths of one sub-ray waiting to be followed; glass splits a path in two.
const STACK: usize = 16;
/// Bit that marks a box (rather than a wall) in the grid's item lists.
const BLOCK_BIT: u32 = 1 << 31;

/// How a surface answers light; see the module docs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Matte,
    Metal,
    Glass,
    Grid,
}

/// A surface material. Fractions are of the incoming light at 850 nm, each in [0, 1].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Material {
    pub kind: Kind,
    /// Lambertian (diffuse) reflectance; for a grid, that of its bars.
    pub albedo: f64,
    /// Fraction mirrored (metal, glass); 0 for matte and grid.
    pub specular: f64,
    /// Fraction transmitted straight on (glass only).
    pub transmission: f64,
    /// Share of a grid's area covered by bars, in [0, 1] (grid only).
    pub coverage: f64,
    /// Distance between a grid's bars, metres (grid only).
    pub pitch: f64,
}

impl Material {
    /// A matte surface of the given albedo.
    pub fn matte(albedo: f64) -> Material {
        Material { kind: Kind::Matte, albedo, specular: 0.0, transmission: 0.0, coverage: 0.0, pitch: 1.0 }
    }

    fn check(&self, index: usize) -> Result<(), String> {
        let fractions = [self.albedo, self.specular, self.transmission, self.coverage];
        if fractions.iter().any(|f| !(0.0..=1.0).contains(f)) {
            return Err(format!("material {index}: fractions must lie in [0, 1]"));
        }
        if self.albedo + self.specular + self.transmission > 1.0 + 1e-9 {
            return Err(format!("material {index}: albedo + specular + transmission exceeds 1"));
        }
        if self.kind == Kind::Grid && !(self.pitch > 0.0 && self.pitch.is_finite()) {
            return Err(format!("material {index}: a grid needs a positive pitch"));
        }
        Ok(())
    }

    /// Whether a point on a grid surface lies on a bar. Bars of width b·pitch run both ways,
    /// centred on multiples of the pitch (so the pattern looks the same from either side), and
    /// cover 1 − (1 − b)² = `coverage` of the area.
    pub(crate) fn on_bar(&self, point: [f64; 3], normal: [f64; 3]) -> bool {
        let bar = 1.0 - (1.0 - self.coverage).sqrt();
        let (u, v) = if normal[2].abs() > 0.5 {
            (point[0], point[1])
        } else {
            let h = (normal[0] * normal[0] + normal[1] * normal[1]).sqrt();
            ((normal[0] * point[1] - normal[1] * point[0]) / h, point[2])
        };
        let near_bar = |x: f64| {
            let s = x / self.pitch;
            (s - s.round()).abs() < 0.5 * bar
        };
        near_bar(u) || near_bar(v)
    }
}

/// A wall: the vertical quad over the floor-plan segment a → b, from z = bottom to z = top.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Wall {
    pub a: [f64; 2],
    pub b: [f64; 2],
    pub bottom: f64,
    pub top: f64,
    pub material: u32,
}

/// A box: a rectangle in plan (centre, half sizes along its own axes, turned by `yaw` radians
/// counter-clockwise), extruded from z = bottom to z = top.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Block {
    pub centre: [f64; 2],
    pub half: [f64; 2],
    pub yaw: f64,
    pub bottom: f64,
    pub top: f64,
    pub material: u32,
}

/// Where a ray first meets the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Ray parameter (metres along a unit direction).
    pub t: f64,
    /// Unit surface normal, turned to face the incoming ray.
    pub normal: [f64; 3],
    pub material: u32,
}

#[derive(Clone, Copy, Debug)]
struct WallGeom {
    a: [f64; 2],
    e: [f64; 2],
    normal: [f64; 2],
    bottom: f64,
    top: f64,
    material: u32,
}

#[derive(Clone, Copy, Debug)]
struct BlockGeom {
    centre: [f64; 2],
    half: [f64; 2],
    cos: f64,
    sin: f64,
    bottom: f64,
    top: f64,
    material: u32,
}

/// Uniform grid over the floor plan; cell (ix, iy) covers [ix·cell, (ix+1)·cell) × [iy·cell, …),
/// as in `raycast`. Items are stored in compressed rows: cell k holds items[starts[k]..starts[k+1]].
#[derive(Clone, Debug)]
struct PlanGrid {
    cell: f64,
    ix0: i32,
    iy0: i32,
    nx: i32,
    ny: i32,
    starts: Vec<u32>,
    items: Vec<u32>,
}

impl PlanGrid {
    fn lo(&self) -> [f64; 2] {
        [self.ix0 as f64 * self.cell, self.iy0 as f64 * self.cell]
    }

    fn hi(&self) -> [f64; 2] {
        [(self.ix0 + self.nx) as f64 * self.cell, (self.iy0 + self.ny) as f64 * self.cell]
    }

    #[inline]
    fn cell_items(&self, ix: i32, iy: i32) -> Option<&[u32]> {
        let (lx, ly) = (ix - self.ix0, iy - self.iy0);
        if lx < 0 || ly < 0 || lx >= self.nx || ly >= self.ny {
            return None;
        }
        let k = (ly * self.nx + lx) as usize;
        Some(&self.items[self.starts[k] as usize..self.starts[k + 1] as usize])
    }
}

/// The world to render: walls, boxes, floor and ceiling, their materials, and the plan grid.
#[derive(Clone, Debug)]
pub struct Scene {
    walls: Vec<WallGeom>,
    blocks: Vec<BlockGeom>,
    materials: Vec<Material>,
    floor_material: u32,
    ceiling_material: u32,
    ceiling_height: f64,
    grid: PlanGrid,
}

impl Scene {
    /// Build a scene and its plan grid of `cell` metres. Errors name the offending item.
    pub fn new(
        walls: &[Wall],
        blocks: &[Block],
        materials: Vec<Material>,
        floor_material: u32,
        ceiling_material: u32,
        ceiling_height: f64,
        cell: f64,
    ) -> Result<Scene, String> {
        if !(cell > 0.0 && cell.is_finite()) {
            return Err(format!("grid cell must be a positive number of metres, got {cell}"));
        }
        if !(ceiling_height > 0.0 && ceiling_height.is_finite()) {
            return Err(format!("ceiling height must be positive, got {ceiling_height}"));
        }
        for (i, m) in materials.iter().enumerate() {
            m.check(i)?;
        }
        let n_mat = materials.len() as u32;
        let known = |m: u32, what: &str| {
            if m < n_mat { Ok(()) } else { Err(format!("{what}: material index {m} out of range ({n_mat} materials)")) }
        };
        known(floor_material, "floor")?;
        known(ceiling_material, "ceiling")?;
        let mut wall_geoms = Vec::with_capacity(walls.len());
        for (i, w) in walls.iter().enumerate() {
            known(w.material, &format!("wall {i}"))?;
            let e = [w.b[0] - w.a[0], w.b[1] - w.a[1]];
            let len = e[0].hypot(e[1]);
            let finite = w.a.iter().chain(&w.b).chain(&[w.bottom, w.top]).all(|v| v.is_finite());
            let valid = finite && len > 0.0 && w.top > w.bottom; // false for NaN too
            if !valid {
                return Err(format!("wall {i} must be finite, of positive length and height"));
            }
            wall_geoms.push(WallGeom {
                a: w.a,
                e,
                normal: [e[1] / len, -e[0] / len],
                bottom: w.bottom,
                top: w.top,
                material: w.material,
            });
        }
        let mut block_geoms = Vec::with_capacity(blocks.len());
        for (i, b) in blocks.iter().enumerate() {
            known(b.material, &format!("box {i}"))?;
            let finite = b.centre.iter().chain(&b.half).chain(&[b.yaw, b.bottom, b.top]).all(|v| v.is_finite());
            let valid = finite && b.half[0] > 0.0 && b.half[1] > 0.0 && b.top > b.bottom;
            if !valid {
                return Err(format!("box {i} must be finite with positive sizes"));
            }
            block_geoms.push(BlockGeom {
                centre: b.centre,
                half: b.half,
                cos: b.yaw.cos(),
                sin: b.yaw.sin(),
                bottom: b.bottom,
                top: b.top,
                material: b.material,
            });
        }
        let grid = build_grid(&wall_geoms, &block_geoms, cell)?;
        Ok(Scene {
            walls: wall_geoms,
            blocks: block_geoms,
            materials,
            floor_material,
            ceiling_material,
            ceiling_height,
            grid,
        })
    }

    pub fn material(&self, index: u32) -> &Material {
        &self.materials[index as usize]
    }

    /// The first surface along the ray o + t·d with t in (t_min, t_max); `d` must be a unit
    /// vector. Walks the plan grid; never loops over all walls.
    pub fn intersect(&self, o: [f64; 3], d: [f64; 3], t_min: f64, t_max: f64) -> Option<Hit> {
        self.intersect_with(o, d, t_min, t_max, &mut Mailbox::for_scene(self))
    }

    /// `intersect` with a caller's mailbox (reused across rays to save its allocation).
    pub fn intersect_with(
        &self,
        o: [f64; 3],
        d: [f64; 3],
        t_min: f64,
        t_max: f64,
        mail: &mut Mailbox,
    ) -> Option<Hit> {
        self.cast(o, d, t_min, t_max, mail, false)
    }

    /// Whether anything lies on the ray o + t·d with t in (t_min, t_max) (a shadow test): the
    /// same answer as `intersect_with(..).is_some()`, but the walk stops at the first hit
    /// instead of looking for the nearest.
    pub fn occluded(&self, o: [f64; 3], d: [f64; 3], t_min: f64, t_max: f64, mail: &mut Mailbox) -> bool {
        self.cast(o, d, t_min, t_max, mail, true).is_some()
    }

    /// The nearest hit, or with `any` the first one found.
    fn cast(&self, o: [f64; 3], d: [f64; 3], t_min: f64, t_max: f64, mail: &mut Mailbox, any: bool) -> Option<Hit> {
        let ray = mail.next_ray();
        let mut best: Option<Hit> = None;
        let mut best_t = t_max;
        // Floor and ceiling first: they bound how far the grid walk has to go.
        let planes = [(0.0, 1.0, self.floor_material), (self.ceiling_height, -1.0, self.ceiling_material)];
        for (height, facing, material) in planes {
            if d[2] * facing < 0.0 {
                let t = (height - o[2]) / d[2];
                if t > t_min && t < best_t {
                    best_t = t;
                    best = Some(Hit { t, normal: [0.0, 0.0, facing], material });
                    if any {
                        return best;
                    }
                }
            }
        }
        let h = (d[0] * d[0] + d[1] * d[1]).sqrt();
        let grid = &self.grid;
        let mut test_items = |items: &[u32], best: &mut Option<Hit>, best_t: &mut f64| {
            for &item in items {
                // A long wall lies in many cells along a ray; test it only once.
                let slot = if item & BLOCK_BIT != 0 { self.walls.len() + (item & !BLOCK_BIT) as usize } else { item as usize };
                if mail.stamps[slot] == ray {
                    continue;
                }
                mail.stamps[slot] = ray;
                let hit = if item & BLOCK_BIT != 0 {
                    hit_block(&self.blocks[(item & !BLOCK_BIT) as usize], o, d, t_min, *best_t)
                } else {
                    hit_wall(&self.walls[item as usize], o, d, t_min, *best_t)
                };
                if let Some(hit) = hit {
                    *best_t = hit.t;
                    *best = Some(hit);
                    if any {
                        return;
                    }
                }
            }
        };
        if h < 1e-12 {
            // Straight up or down: the ray never leaves the cell it starts in.
            let (ix, iy) = (floor_i32(o[0] / grid.cell), floor_i32(o[1] / grid.cell));
            if let Some(items) = grid.cell_items(ix, iy) {
                test_items(items, &mut best, &mut best_t);
            }
            return best;
        }
        let inv_h = 1.0 / h;
        let u = [d[0] * inv_h, d[1] * inv_h];
        // Clip the horizontal ray (arc length s = t·h) to the grid's rectangle; a ray that
        // starts inside needs no clip: the walk stops where it leaves the grid.
        let (lo, hi) = (grid.lo(), grid.hi());
        let inside = lo[0] < o[0] && o[0] < hi[0] && lo[1] < o[1] && o[1] < hi[1];
        let Some((s_in, s_out)) = (if inside { Some((0.0, f64::INFINITY)) } else { clip_to_rect([o[0], o[1]], u, lo, hi) })
        else {
            return best;
        };
        let s_lo = s_in.max(t_min * h);
        let s_hi = s_out.min(best_t * h);
        if s_lo >= s_hi {
            return best;
        }
        // Start a hair inside so the first cell is inside the grid (geometry keeps a margin).
        let s_start = s_lo + 1e-9 * (1.0 + s_lo.abs());
        let start = [o[0] + s_start * u[0], o[1] + s_start * u[1]];
        traverse(start, u, s_hi - s_start, grid.cell, |ix, iy, _, s_exit| {
            let Some(items) = grid.cell_items(ix, iy) else { return false };
            test_items(items, &mut best, &mut best_t);
            // Hits found beyond this cell stay candidates; stop once the nearest one lies in it.
            !(any && best.is_some()) && best_t * h > s_start + s_exit
        });
        best
    }
}

/// Per-ray marks of the primitives already tested (mailboxing): a primitive that spans many
/// grid cells is intersected once per ray. One per worker; `next_ray` starts a new ray.
#[derive(Clone, Debug)]
pub struct Mailbox {
    stamps: Vec<u32>,
    ray: u32,
}

impl Mailbox {
    pub fn for_scene(scene: &Scene) -> Mailbox {
        Mailbox { stamps: vec![0; scene.walls.len() + scene.blocks.len()], ray: 0 }
    }

    fn next_ray(&mut self) -> u32 {
        self.ray = self.ray.wrapping_add(1);
        if self.ray == 0 {
            // After 2³² rays the stamps could repeat: clear them.
            self.stamps.fill(0);
            self.ray = 1;
        }
        self.ray
    }
}

/// Parametric interval [s_in, s_out] (s >= 0 not enforced) of the 2D ray p + s·u inside the
/// rectangle [lo, hi]; None if it misses.
fn clip_to_rect(p: [f64; 2], u: [f64; 2], lo: [f64; 2], hi: [f64; 2]) -> Option<(f64, f64)> {
    let (mut s0, mut s1) = (f64::NEG_INFINITY, f64::INFINITY);
    for k in 0..2 {
        if u[k] == 0.0 {
            if p[k] < lo[k] || p[k] > hi[k] {
                return None;
            }
        } else {
            let a = (lo[k] - p[k]) / u[k];
            let b = (hi[k] - p[k]) / u[k];
            s0 = s0.max(a.min(b));
            s1 = s1.min(a.max(b));
        }
    }
    (s0 <= s1).then_some((s0, s1))
}

#[inline]
fn cross2(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[1] - a[1] * b[0]
}

#[inline]
fn hit_wall(w: &WallGeom, o: [f64; 3], d: [f64; 3], t_min: f64, t_max: f64) -> Option<Hit> {
    // o + t·d = a + s·e in plan: t = ((a − o) × e)/(d × e), s = ((a − o) × d)/(d × e).
    let dd = [d[0], d[1]];
    let denom = cross2(dd, w.e);
    if denom.abs() < 1e-15 {
        return None; // parallel to the wall (or vertical): it cannot cross it
    }
    let ao = [w.a[0] - o[0], w.a[1] - o[1]];
    let t = cross2(ao, w.e) / denom;
    if !(t > t_min && t < t_max) {
        return None;
    }
    let s = cross2(ao, dd) / denom;
    let z = o[2] + t * d[2];
    if !(0.0..=1.0).contains(&s) || z < w.bottom || z > w.top {
        return None;
    }
    let facing = if w.normal[0] * d[0] + w.normal[1] * d[1] > 0.0 { -1.0 } else { 1.0 };
    Some(Hit { t, normal: [facing * w.normal[0], facing * w.normal[1], 0.0], material: w.material })
}

#[inline]
fn hit_block(b: &BlockGeom, o: [f64; 3], d: [f64; 3], t_min: f64, t_max: f64) -> Option<Hit> {
    // Slab test in the box's own frame (its axes turned by yaw in plan): the plan axes first,
    // since most candidates from the grid miss the box in plan and leave early.
    let rel = [o[0] - b.centre[0], o[1] - b.centre[1]];
    let p = [b.cos * rel[0] + b.sin * rel[1], -b.sin * rel[0] + b.cos * rel[1], o[2]];
    let q = [b.cos * d[0] + b.sin * d[1], -b.sin * d[0] + b.cos * d[1], d[2]];
    let mid = [0.0, 0.0, 0.5 * (b.bottom + b.top)];
    let half = [b.half[0], b.half[1], 0.5 * (b.top - b.bottom)];
    let (mut t_near, mut t_far) = (f64::NEG_INFINITY, f64::INFINITY);
    let (mut axis_near, mut axis_far) = (0usize, 0usize);
    for k in 0..3 {
        let rel = p[k] - mid[k];
        if q[k].abs() < 1e-15 {
            if rel.abs() > half[k] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / q[k];
        let (ta, tb) = ((-half[k] - rel) * inv, (half[k] - rel) * inv);
        let (t0, t1) = if inv > 0.0 { (ta, tb) } else { (tb, ta) };
        if t0 > t_near {
            t_near = t0;
            axis_near = k;
        }
        if t1 < t_far {
            t_far = t1;
            axis_far = k;
        }
        if t_near > t_far || t_far <= t_min || t_near >= t_max {
            return None;
        }
    }
    // From outside, the entry face; from inside (a ray passing through glass), the exit face.
    let (t, axis) = if t_near > t_min { (t_near, axis_near) } else { (t_far, axis_far) };
    if !(t > t_min && t < t_max) {
        return None;
    }
    let side = -q[axis].signum(); // the face's side that the ray meets
    let normal = match axis {
        0 => [b.cos * side, b.sin * side, 0.0],
        1 => [-b.sin * side, b.cos * side, 0.0],
        _ => [0.0, 0.0, side],
    };
    Some(Hit { t, normal, material: b.material })
}

/// Whether the segment a → b touches the axis-aligned square [lo, hi] (both closed).
fn segment_touches_box(a: [f64; 2], b: [f64; 2], lo: [f64; 2], hi: [f64; 2]) -> bool {
    let u = [b[0] - a[0], b[1] - a[1]];
    let (mut s0, mut s1) = (0.0f64, 1.0f64);
    for k in 0..2 {
        if u[k] == 0.0 {
            if a[k] < lo[k] || a[k] > hi[k] {
                return false;
            }
        } else {
            let p = (lo[k] - a[k]) / u[k];
            let q = (hi[k] - a[k]) / u[k];
            s0 = s0.max(p.min(q));
            s1 = s1.min(p.max(q));
        }
    }
    s0 <= s1
}

/// Bin every primitive into the cells its footprint touches. Cells are padded by a tiny slack so
/// a wall that runs exactly along a cell boundary is listed on both sides, and the grid keeps an
/// empty margin of one cell around all geometry.
/// Fails for a plan too wide for its cells (more than MAX_PLAN_CELLS), instead of overflowing.
fn build_grid(walls: &[WallGeom], blocks: &[BlockGeom], cell: f64) -> Result<PlanGrid, String> {
    let mut footprints: Vec<([f64; 2], [f64; 2])> = Vec::with_capacity(walls.len() + blocks.len());
    for w in walls {
        let b = [w.a[0] + w.e[0], w.a[1] + w.e[1]];
        footprints.push(([w.a[0].min(b[0]), w.a[1].min(b[1])], [w.a[0].max(b[0]), w.a[1].max(b[1])]));
    }
    for b in blocks {
        let ex = b.half[0] * b.cos.abs() + b.half[1] * b.sin.abs();
        let ey = b.half[0] * b.sin.abs() + b.half[1] * b.cos.abs();
        footprints.push(([b.centre[0] - ex, b.centre[1] - ey], [b.centre[0] + ex, b.centre[1] + ey]));
    }
    let (mut lo, mut hi) = ([0.0f64; 2], [cell; 2]);
    if let Some(first) = footprints.first() {
        (lo, hi) = *first;
        for (l, h) in &footprints {
            for k in 0..2 {
                lo[k] = lo[k].min(l[k]);
                hi[k] = hi[k].max(h[k]);
            }
        }
    }
    let cells = ((hi[0] - lo[0]) / cell + 3.0) * ((hi[1] - lo[1]) / cell + 3.0);
    let far = lo.iter().chain(&hi).fold(0.0f64, |m, v| m.max(v.abs())) / cell;
    if !(cells <= MAX_PLAN_CELLS && far < 1e9) {
        return Err(format!(
            "the plan spans {:.4} m × {:.4} m: too large for the renderer's {cell} m grid ({MAX_PLAN_CELLS} cells at most)",
            hi[0] - lo[0],
            hi[1] - lo[1]
        ));
    }
    let ix0 = (lo[0] / cell).floor() as i32 - 1;
    let iy0 = (lo[1] / cell).floor() as i32 - 1;
    let nx = (hi[0] / cell).floor() as i32 + 2 - ix0;
    let ny = (hi[1] / cell).floor() as i32 + 2 - iy0;
    let mut lists: Vec<Vec<u32>> = vec![Vec::new(); (nx * ny) as usize];
    let slack = 1e-9 * (1.0 + cell);
    let cell_of = |v: f64| (v / cell).floor() as i32;
    for (index, (l, h)) in footprints.iter().enumerate() {
        let (cx0, cx1) = (cell_of(l[0] - slack), cell_of(h[0] + slack));
        let (cy0, cy1) = (cell_of(l[1] - slack), cell_of(h[1] + slack));
        for iy in cy0..=cy1 {
            for ix in cx0..=cx1 {
                let box_lo = [ix as f64 * cell - slack, iy as f64 * cell - slack];
                let box_hi = [(ix + 1) as f64 * cell + slack, (iy + 1) as f64 * cell + slack];
                let item = if index < walls.len() {
                    let w = &walls[index];
                    let b = [w.a[0] + w.e[0], w.a[1] + w.e[1]];
                    if !segment_touches_box(w.a, b, box_lo, box_hi) {
                        continue;
                    }
                    index as u32
                } else {
                    // The box's bounding rectangle: conservative, and boxes are few.
                    (index - walls.len()) as u32 | BLOCK_BIT
                };
                lists[((iy - iy0) * nx + (ix - ix0)) as usize].push(item);
            }
        }
    }
    let mut starts = Vec::with_capacity(lists.len() + 1);
    let mut items = Vec::new();
    starts.push(0u32);
    for list in lists {
        items.extend(list);
        starts.push(items.len() as u32);
    }
    Ok(PlanGrid { cell, ix0, iy0, nx, ny, starts, items })
}

/// The most cells the renderer's plan grid may have (a list each: 24 bytes, so 1.6 GB at most).
const MAX_PLAN_CELLS: f64 = (1u64 << 26) as f64;

// --- the camera side ---------------------------------------------------------------------

/// A planar mirror in the camera frame: the plane {x : n·x = d} (n unit, pointing away from the
/// camera, d > 0), a convex outline on it, and its reflectivity.
#[derive(Clone, Debug, PartialEq)]
pub struct Mirror {
    pub normal: [f64; 3],
    pub d: f64,
    pub polygon: Vec<[f64; 3]>,
    pub reflectivity: f64,
}

impl Mirror {
    fn check(&self, index: usize) -> Result<(), String> {
        let n = self.normal;
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if !((len - 1.0).abs() < 1e-9 && self.d > 0.0 && self.d.is_finite()) {
            return Err(format!("mirror {index}: the normal must be a unit vector and d > 0"));
        }
        if self.polygon.len() < 3 || self.polygon.iter().flatten().any(|v| !v.is_finite()) {
            return Err(format!("mirror {index}: the outline needs >= 3 finite vertices"));
        }
        // Twice the outline's area, projected on the normal (shoelace in 3D): an outline of
        // coincident or collinear vertices would cover the whole plane or none of it.
        let o = self.polygon[0];
        let area2: f64 = (1..self.polygon.len() - 1)
            .map(|i| dot(n, cross(sub(self.polygon[i], o), sub(self.polygon[i + 1], o))))
            .sum();
        if !(area2.abs() > 1e-12) {
            return Err(format!("mirror {index}: the outline encloses no area (coincident or collinear vertices)"));
        }
        if !(0.0..=1.0).contains(&self.reflectivity) {
            return Err(format!("mirror {index}: reflectivity must lie in [0, 1]"));
        }
        Ok(())
    }

    /// Distance along the unit ray from the camera centre to this mirror, if it meets the
    /// reflective side inside the outline.
    fn hit_from_centre(&self, v: [f64; 3]) -> Option<f64> {
        let approach = dot(self.normal, v);
        if approach <= 0.0 {
            return None;
        }
        let t = self.d / approach;
        let p = scale(v, t);
        let k = self.polygon.len();
        let (mut pos, mut neg) = (false, false);
        let tol = 1e-12 * (1.0 + t);
        for i in 0..k {
            let a = self.polygon[i];
            let b = self.polygon[(i + 1) % k];
            let side = dot(self.normal, cross(sub(b, a), sub(p, a)));
            pos |= side > tol;
            neg |= side < -tol;
        }
        (!(pos && neg)).then_some(t)
    }
}

/// One sub-ray as it leaves the optics, in the camera frame: where it starts (on a mirror, or at
/// the camera centre if it misses every mirror), its unit direction, the path length so far, and
/// the round-trip (g2) and one-way (g1) light factors so far. g2 = 0 marks a ray that does not
/// exist (outside the lens model).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SubRay {
    pub origin: [f64; 3],
    pub dir: [f64; 3],
    pub path: f64,
    pub g2: f64,
    pub g1: f64,
}

/// The fixed optics: every sub-ray of every pixel after the mirrors, and the mount.
#[derive(Clone, Debug)]
pub struct Rig {
    pub height: usize,
    pub width: usize,
    pub sub_rays: usize,
    rays: Vec<SubRay>,
    mirrors: Vec<Mirror>,
    robot_t_camera: [[f64; 4]; 3],
}

impl Rig {
    /// `dirs`: H·W·S camera-frame directions, pixel-major ([row][col][sub]); NaN rows are rays
    /// the lens does not have. Each is sent to the nearest mirror it meets and reflected there.
    pub fn new(
        dirs: &[[f64; 3]],
        height: usize,
        width: usize,
        sub_rays: usize,
        mirrors: &[Mirror],
        robot_t_camera: [[f64; 4]; 3],
    ) -> Result<Rig, String> {
        let count = height.checked_mul(width).and_then(|p| p.checked_mul(sub_rays));
        if height == 0 || width == 0 || sub_rays == 0 || count != Some(dirs.len()) {
            return Err(format!(
                "{} directions do not fill {height}×{width} pixels × {sub_rays} sub-rays",
                dirs.len()
            ));
        }
        for (i, m) in mirrors.iter().enumerate() {
            m.check(i)?;
        }
        if robot_t_camera.iter().flatten().any(|v| !v.is_finite()) {
            return Err("robot_T_camera must be finite".into());
        }
        // A rigid mount: its rotation orthonormal and not a reflection.
        let r = |i: usize, j: usize| robot_t_camera[i][j];
        for i in 0..3 {
            for j in 0..3 {
                let rrt = (0..3).map(|k| r(i, k) * r(j, k)).sum::<f64>();
                if (rrt - if i == j { 1.0 } else { 0.0 }).abs() > 1e-6 {
                    return Err("robot_T_camera's rotation must be orthonormal (a rigid mount)".into());
                }
            }
        }
        let det = r(0, 0) * (r(1, 1) * r(2, 2) - r(1, 2) * r(2, 1)) - r(0, 1) * (r(1, 0) * r(2, 2) - r(1, 2) * r(2, 0))
            + r(0, 2) * (r(1, 0) * r(2, 1) - r(1, 1) * r(2, 0));
        if det < 0.0 {
            return Err("robot_T_camera's rotation is a reflection (determinant −1)".into());
        }
        let rays = dirs.iter().map(|&v| through_mirrors(v, mirrors)).collect();
        Ok(Rig { height, width, sub_rays, rays, mirrors: mirrors.to_vec(), robot_t_camera })
    }

    /// The sub-rays after the optics, pixel-major.
    pub fn rays(&self) -> &[SubRay] {
        &self.rays
    }

    /// world_T_camera (3×4) for a robot pose (x, y, θ).
    pub fn world_t_camera(&self, pose: [f64; 3]) -> [[f64; 4]; 3] {
        let (s, c) = pose[2].sin_cos();
        let m = &self.robot_t_camera;
        let mut out = [[0.0; 4]; 3];
        for j in 0..4 {
            out[0][j] = c * m[0][j] - s * m[1][j];
            out[1][j] = s * m[0][j] + c * m[1][j];
            out[2][j] = m[2][j];
        }
        out[0][3] += pose[0];
        out[1][3] += pose[1];
        out
    }
}

fn through_mirrors(v: [f64; 3], mirrors: &[Mirror]) -> SubRay {
    let len = norm(v);
    if !(len > 0.0 && len.is_finite()) {
        return SubRay { origin: [0.0; 3], dir: [0.0, 0.0, 1.0], path: 0.0, g2: 0.0, g1: 0.0 };
    }
    let v = scale(v, 1.0 / len);
    let mut nearest: Option<(f64, &Mirror)> = None;
    for m in mirrors {
        if let Some(t) = m.hit_from_centre(v) {
            if nearest.is_none_or(|(best, _)| t < best) {
                nearest = Some((t, m));
            }
        }
    }
    match nearest {
        Some((t, m)) => {
            let r = m.reflectivity;
            SubRay { origin: scale(v, t), dir: reflect(v, m.normal), path: t, g2: r * r, g1: r }
        }
        None => SubRay { origin: [0.0; 3], dir: v, path: 0.0, g2: 1.0, g1: 1.0 },
    }
}

// --- rendering ---------------------------------------------------------------------------

/// Signal scale, light-path limits and the light model.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderParams {
    /// Modulation frequency, Hz.
    pub f_mod: f64,
    /// Amplitude (sample units) of an albedo-1 Lambertian target facing the camera at 1 m.
    pub amplitude_at_1m: f64,
    /// Specular bounces (metal, glass) followed after the first surface.
    pub max_bounces: u32,
    /// Paths whose round-trip factor g2 falls below this are dropped.
    pub min_gain: f64,
    /// The LEDs beside the lens (light.rs); None: the coaxial source (light follows the view).
    pub illumination: Option<Illumination>,
    /// Secondary rays per pixel for one diffuse interreflection (multipath); 0: none.
    pub multipath_rays: u32,
    /// Half-width (pixels) of the window over which a pixel's interreflection is averaged with
    /// its neighbours' that see the same surface (`smooth_row`, `smoothed_column`); 0: each
    /// pixel alone.
    pub multipath_window: u32,
    /// The light of the interreflections' sources: the LEDs themselves (the same light as the
    /// direct returns', so a surface sends the light it is seen to get); without LEDs, one
    /// source at the lens centre with the LEDs' emission profile.
    pub bounce: Illumination,
    /// Seed of the secondary rays' directions.
    pub seed: u64,
}

/// Up to this many secondary rays per sub-ray.
pub const MAX_SECONDARY: usize = 16;

/// What `trace` needs besides the ray: the pose's light sources and this sub-ray's secondary
/// rays (two uniforms each) with the weight of each.
pub struct Lighting<'a> {
    /// The LEDs, for the direct light.
    pub light: &'a PoseLight,
    /// The LEDs' sources that may light this sub-ray's points, and how far (`light::candidate_masks`).
    pub reach: SubRayLight,
    /// The light of the interreflections' sources (`RenderParams::bounce`), tested for
    /// occlusion (`PoseLight::paths`).
    pub bounce_light: &'a PoseLight,
    pub secondary: &'a [[f64; 2]],
    pub secondary_weight: f64,
}

/// What one pixel (or one sub-ray) collects: the phasor (re, im), Σ|p|, and the ambient
/// brightness Σ g1·albedo. Pixel values are means over the sub-rays.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Return {
    pub re: f64,
    pub im: f64,
    pub magnitude: f64,
    pub ambient: f64,
    /// (phase, cos, sin) of the first path added: a pixel's sub-rays mostly see one surface,
    /// their phases within a few hundredths of a radian of each other.
    reference: Option<(f64, f64, f64)>,
    /// The interreflection (multipath), kept apart from the rest until `render_with` writes
    /// the pixel (after averaging it with its neighbours').
    pub indirect: Indirect,
}

/// A pixel's interreflection: the sum of its secondary paths' phasors and magnitudes, and the
/// surface its secondary rays left from. Two rays per pixel make a noisy estimate of a smooth
/// quantity; `smooth_row` and `smoothed_column` average it over the neighbouring pixels that
/// see the same surface, through `smoothable()`: the phasor per unit of the surface's
/// direct-light scale with the phase of the pixel's own path taken out, which varies slowly
/// along a surface.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Indirect {
    pub re: f64,
    pub im: f64,
    pub magnitude: f64,
    /// Σ over the sub-rays that sent secondary rays of their direct-light scale × rays × weight.
    scale: f64,
    /// Σ scale·(one-way path to the surface) and Σ scale·(surface point).
    path: f64,
    point: [f64; 3],
    /// The first such sub-ray's surface: unit normal and plane offset (n·x).
    normal: [f64; 3],
    offset: f64,
    /// Sub-rays of the pixel sent secondary rays from different surfaces (an edge).
    mixed: bool,
    /// As `Return::reference`: the paths through the LEDs' images differ by centimetres.
    reference: Option<(f64, f64, f64)>,
}

impl Indirect {
    fn add(&mut self, amplitude: f64, phase: f64) {
        let (s, c) = sin_cos_near(&mut self.reference, phase);
        self.re += amplitude * c;
        self.im += amplitude * s;
        self.magnitude += amplitude;
    }

    /// The sub-ray at `point` (one-way path `path`, facing normal `normal`) sent secondary
    /// rays worth `scale` (direct-light scale × rays × weight).
    fn sent_from(&mut self, w: f64, path: f64, point: [f64; 3], normal: [f64; 3]) {
        let offset = dot(normal, point);
        if self.scale <= 0.0 {
            (self.normal, self.offset) = (normal, offset);
        } else if dot(self.normal, normal) < SAME_NORMAL || (self.offset - offset).abs() > SAME_PLANE {
            self.mixed = true;
        }
        self.scale += w;
        self.path += w * path;
        self.point = add(self.point, scale(point, w));
    }

    /// What the averaging needs of this pixel: None without secondary rays or where they
    /// left from different surfaces (the pixel keeps its own estimate).
    fn smoothable(&self, k: f64) -> Option<Smoothable> {
        if self.scale <= 0.0 || self.mixed {
            return None;
        }
        let inv = 1.0 / self.scale;
        let (s, c) = (k * self.path * inv).sin_cos();
        // The phasor per unit scale, turned back by the phase of the mean path (e^{−ik·path}).
        let e = [(self.re * c + self.im * s) * inv, (self.im * c - self.re * s) * inv];
        Some(Smoothable {
            normal: self.normal.map(|v| v as f32),
            offset: self.offset as f32,
            point: scale(self.point, inv).map(|v| v as f32),
            value: [e[0], e[1], self.magnitude * inv],
            turn: [c, s],
            scale: self.scale,
        })
    }
}

/// Two sub-rays' surfaces are one plane if their normals are within 2.6° and their planes 2 cm.
const SAME_NORMAL: f64 = 0.999;
const SAME_PLANE: f64 = 0.02;
/// Neighbours whose surface points lie farther apart than this (m) are not averaged: the
/// interreflection changes over the distance to the nearest corner, rarely less than 0.2 m.
const SMOOTH_RADIUS: f64 = 0.2;

/// Paths whose phase lies this close (radians) to the pixel's first path turn its cos and sin
/// by a series instead of calling sin_cos (error below 3·10⁻¹⁵).
const NEAR_PHASE: f64 = 0.1;

impl Return {
    /// Add a light path's phasor: `amplitude`·e^{i·phase}.
    fn add(&mut self, amplitude: f64, phase: f64) {
        let (s, c) = sin_cos_near(&mut self.reference, phase);
        self.re += amplitude * c;
        self.im += amplitude * s;
        self.magnitude += amplitude;
    }
}

/// sin and cos of `phase`, by a series from `reference` (phase, cos, sin) where the phase lies
/// within NEAR_PHASE of it; the first phase seen becomes the reference.
#[inline]
fn sin_cos_near(reference: &mut Option<(f64, f64, f64)>, phase: f64) -> (f64, f64) {
    match *reference {
        Some((p0, c0, s0)) if (phase - p0).abs() < NEAR_PHASE => {
            // e^{iφ} = e^{iφ0}·e^{iδ}, e^{iδ} by its Taylor series (terms to δ⁸: the
            // remainder is below δ⁹/9! < 3·10⁻¹⁵ for |δ| < 0.1).
            let d = phase - p0;
            let d2 = d * d;
            let sd = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0)));
            let cd = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0)));
            (s0 * cd + c0 * sd, c0 * cd - s0 * sd)
        }
        _ => {
            let (s, c) = phase.sin_cos();
            if reference.is_none() {
                *reference = Some((phase, c, s));
            }
            (s, c)
        }
    }
}

#[derive(Clone, Copy, Debug)]
struct Segment {
    origin: [f64; 3],
    dir: [f64; 3],
    path: f64,
    g2: f64,
    g1: f64,
    bounces: u32,
    passes: u32,
}

/// Scratch space of one worker: the mailbox and the stack of light paths still to follow.
#[derive(Clone, Debug)]
pub struct Workspace {
    mail: Mailbox,
    pending: Vec<Segment>,
}

impl Workspace {
    pub fn for_scene(scene: &Scene) -> Workspace {
        Workspace { mail: Mailbox::for_scene(scene), pending: Vec::with_capacity(STACK) }
    }
}

/// Follow one ray (world frame) through the scene and add what comes back to `acc`.
pub fn trace(scene: &Scene, params: &RenderParams, ray: &SubRay, acc: &mut Return, work: &mut Workspace) {
    trace_lit(scene, params, ray, None, acc, work)
}

/// `trace` with the light model of light.rs: with `params.illumination`, a diffuse point seen
/// without metal or glass on the way is lit by the LEDs' paths (not by a coaxial source), and
/// the first such point sends `lighting.secondary` rays for one interreflection. Points seen
/// through metal, glass or grid holes keep the coaxial model (the LEDs' light is not followed
/// through them).
pub fn trace_lit(
    scene: &Scene,
    params: &RenderParams,
    ray: &SubRay,
    lighting: Option<&Lighting>,
    acc: &mut Return,
    work: &mut Workspace,
) {
    if ray.g2 <= 0.0 {
        return;
    }
    // Phase per metre of one-way path: the light travels it twice.
    let k = 4.0 * std::f64::consts::PI * params.f_mod / SPEED_OF_LIGHT;
    work.pending.clear();
    let mut current =
        Some(Segment { origin: ray.origin, dir: ray.dir, path: ray.path, g2: ray.g2, g1: ray.g1, bounces: 0, passes: 0 });
    // Only glass splits a path in two; the second half waits on the stack.
    while let Some(seg) = current.take().or_else(|| work.pending.pop()) {
        let Some(hit) = scene.intersect_with(seg.origin, seg.dir, T_MIN, f64::INFINITY, &mut work.mail) else { continue };
        let point = add(seg.origin, scale(seg.dir, hit.t));
        let r = seg.path + hit.t;
        let m = scene.material(hit.material);
        if m.kind == Kind::Grid && !m.on_bar(point, hit.normal) {
            if seg.passes < MAX_PASSES {
                current = Some(Segment { origin: point, path: r, passes: seg.passes + 1, ..seg });
            }
            continue;
        }
        if m.albedo > 0.0 {
            let direct = seg.bounces == 0 && seg.passes == 0;
            let scale_p = params.amplitude_at_1m * seg.g1 * m.albedo;
            match lighting {
                Some(l) if direct && params.illumination.is_some() => {
                    // Light paths LED → (mirror) → point, view path point → (mirror) → pixel.
                    // They differ by a few cm (< 0.03 rad at 20 MHz), so their phasors add as one
                    // of the summed gain at the gain-weighted mean length (relative error
                    // < 0.03²/2): one sine and cosine per point instead of one per LED.
                    let (mut gains, mut lengths) = (0.0, 0.0);
                    let candidates = if hit.t > l.reach.direct_reach {
                        l.reach.candidates & !l.light.direct_bits()
                    } else {
                        l.reach.candidates
                    };
                    l.light.paths(scene, point, hit.normal, candidates, false, &mut work.mail, |gain, length| {
                        gains += gain;
                        lengths += gain * length;
                    });
                    if gains > 0.0 {
                        acc.add(scale_p * gains, 0.5 * k * (r + lengths / gains));
                    }
                }
                _ => {
                    let cos = -dot(hit.normal, seg.dir);
                    acc.add(params.amplitude_at_1m * seg.g2 * m.albedo * cos / (r * r), k * r);
                }
            }
            acc.ambient += seg.g1 * m.albedo;
            if let Some(l) = lighting.filter(|l| direct && !l.secondary.is_empty()) {
                let weight = scale_p * l.secondary_weight;
                for &u in l.secondary {
                    l.bounce_light.bounce(scene, point, hit.normal, u, &mut work.mail, |gain, length| {
                        acc.indirect.add(weight * gain, 0.5 * k * (r + length));
                    });
                }
                acc.indirect.sent_from(weight * l.secondary.len() as f64, r, point, hit.normal);
            }
        }
        if m.specular > 0.0 && seg.bounces < params.max_bounces && seg.g2 * m.specular * m.specular >= params.min_gain {
            current = Some(Segment {
                origin: point,
                dir: reflect(seg.dir, hit.normal),
                path: r,
                g2: seg.g2 * m.specular * m.specular,
                g1: seg.g1 * m.specular,
                bounces: seg.bounces + 1,
                passes: seg.passes,
            });
        }
        let t = m.transmission;
        if t > 0.0 && seg.passes < MAX_PASSES && seg.g2 * t * t >= params.min_gain {
            let through = Segment { origin: point, path: r, g2: seg.g2 * t * t, g1: seg.g1 * t, passes: seg.passes + 1, ..seg };
            if current.is_none() {
                current = Some(through);
            } else if work.pending.len() < STACK {
                work.pending.push(through);
            }
        }
    }
}

/// Per sub-ray of the rig, the LEDs' light sources that may light it (`light::candidate_masks`);
/// None without LEDs. Fixed for a rig and its light: computed once and handed to
/// `render_with`.
pub fn light_masks(rig: &Rig, params: &RenderParams) -> Option<Vec<SubRayLight>> {
    params.illumination.as_ref().map(|light| candidate_masks(light, &rig.mirrors, &rig.rays))
}

/// Render the frames of `poses` into `out`: (frame, row, col, [re, im, Σ|p|, ambient]) as f32,
/// each value the mean over the pixel's sub-rays. Runs on the current rayon pool, one image
/// row per task; the result does not depend on the number of threads.
pub fn render(scene: &Scene, rig: &Rig, params: &RenderParams, poses: &[[f64; 3]], out: &mut [f32]) {
    render_with(scene, rig, params, light_masks(rig, params).as_deref(), poses, poses, out)
}

/// `render` with the rig's `light_masks` computed beforehand (None: every source is tested).
/// Image i's secondary rays draw their random numbers from `keys[i]` (with `params.seed`):
/// `poses` itself for frames taken at one instant; for the four samples of a frame taken while
/// the robot moves, the frame's one pose for all four (common random numbers). The
/// interreflection of a real scene is a smooth function of the pose; four independent
/// Monte-Carlo estimates of it would differ by their noise (more than 5 % of the phasor in one
/// pixel of seven, even averaged over the neighbours), which the 4-tap decoding turns into
/// errors no camera makes.
pub fn render_with(
    scene: &Scene,
    rig: &Rig,
    params: &RenderParams,
    masks: Option<&[SubRayLight]>,
    poses: &[[f64; 3]],
    keys: &[[f64; 3]],
    out: &mut [f32],
) {
    let (h, w, s) = (rig.height, rig.width, rig.sub_rays);
    assert!(masks.is_none_or(|m| m.len() == rig.rays.len()), "one light mask per sub-ray");
    assert_eq!(keys.len(), poses.len(), "one random-number key per pose");
    assert_eq!(out.len(), poses.len() * h * w * 4, "output buffer size");
    let transforms: Vec<[[f64; 4]; 3]> = poses.iter().map(|&p| rig.world_t_camera(p)).collect();
    let lit = params.illumination.is_some() || params.multipath_rays > 0;
    let coaxial = Illumination::coaxial();
    let source = params.illumination.as_ref().unwrap_or(&coaxial);
    let centre = &params.bounce;
    let per_pose = |light: &Illumination| -> Vec<PoseLight> {
        if lit { transforms.iter().map(|m| PoseLight::new(light, &rig.mirrors, m)).collect() } else { vec![] }
    };
    let (lights, bounce_lights) = (per_pose(source), per_pose(centre));
    // The pixel's secondary rays, spread over its sub-rays: sub-ray j sends rays j, j + s, ...
    let total = params.multipath_rays as usize;
    let weight = if total > 0 { s as f64 / total as f64 } else { 0.0 };
    // Image row `row_index` (over all frames) into `returns`, one per pixel.
    let trace_row = |row_index: usize, returns: &mut [Return]| {
        let mut work = Workspace::for_scene(scene);
        let frame = row_index / h;
        let m = &transforms[frame];
        let first = (row_index % h) * w * s;
        let hash = pose_hash(params.seed, keys[frame]);
        let mut secondary = [[0.0f64; 2]; MAX_SECONDARY];
        for (col, acc) in returns.iter_mut().enumerate() {
            *acc = Return::default();
            let pixel = ((row_index % h) * w + col) as u64;
            for (j, sub) in rig.rays[first + col * s..first + (col + 1) * s].iter().enumerate() {
                let world = SubRay { origin: apply(m, sub.origin), dir: rotate(m, sub.dir), ..*sub };
                if !lit {
                    trace(scene, params, &world, acc, &mut work);
                    continue;
                }
                let mut count = 0;
                let mut ray = j;
                while ray < total && count < MAX_SECONDARY {
                    secondary[count] = uniforms_of_pose(hash, pixel, ray as u64);
                    count += 1;
                    ray += s;
                }
                let lighting = Lighting {
                    light: &lights[frame],
                    reach: masks.map_or(SubRayLight::ALL, |m| m[first + col * s + j]),
                    bounce_light: &bounce_lights[frame],
                    secondary: &secondary[..count],
                    secondary_weight: weight,
                };
                trace_lit(scene, params, &world, Some(&lighting), acc, &mut work);
            }
        }
    };
    let inv = 1.0 / s as f64;
    let write = |acc: &Return, indirect: [f64; 3], px: &mut [f32]| {
        let (re, im) = (((acc.re + indirect[0]) * inv) as f32, ((acc.im + indirect[1]) * inv) as f32);
        px[0] = re;
        px[1] = im;
        // |Σp| <= Σ|p| holds exactly; keep it true after rounding to f32.
        px[2] = (((acc.magnitude + indirect[2]) * inv) as f32).max(re.hypot(im) * (1.0 + 4.0 * f32::EPSILON));
        px[3] = (acc.ambient * inv) as f32;
    };
    let own = |a: &Return| [a.indirect.re, a.indirect.im, a.indirect.magnitude];
    if total == 0 || params.multipath_window == 0 {
        out.par_chunks_mut(w * 4).enumerate().for_each(|(row_index, row)| {
            let mut returns = vec![Return::default(); w];
            trace_row(row_index, &mut returns);
            for (acc, px) in returns.iter().zip(row.chunks_exact_mut(4)) {
                write(acc, own(acc), px);
            }
        });
        return;
    }
    // With multipath: a few frames at a time, every pixel traced, then each pixel's
    // interreflection averaged with its neighbours' (`smooth_row`, `smoothed_column`).
    let k = 4.0 * std::f64::consts::PI * params.f_mod / SPEED_OF_LIGHT;
    let per_frame = h * w;
    let mut pixels = vec![None; SMOOTH_FRAMES.min(poses.len()) * per_frame];
    let mut rows = vec![[0.0; 3]; pixels.len()];
    let window = params.multipath_window as usize;
    for (chunk, out_chunk) in out.chunks_mut(SMOOTH_FRAMES * per_frame * 4).enumerate() {
        let pixels = &mut pixels[..out_chunk.len() / 4];
        let rows = &mut rows[..pixels.len()];
        // Each pixel without its interreflection, and what its interreflection needs to be averaged.
        out_chunk.par_chunks_mut(w * 4).zip(pixels.par_chunks_mut(w)).enumerate().for_each(|(r, (row, side))| {
            let mut returns = vec![Return::default(); w];
            trace_row(chunk * SMOOTH_FRAMES * h + r, &mut returns);
            for ((acc, px), p) in returns.iter().zip(row.chunks_exact_mut(4)).zip(side.iter_mut()) {
                *p = acc.indirect.smoothable(k);
                write(acc, if p.is_some() { [0.0; 3] } else { own(acc) }, px);
            }
        });
        // The interreflection averaged along each image row, then along each column of those
        // row averages (`smooth_row`, `smoothed_column`), added to the pixel.
        rows.par_chunks_mut(w).zip(pixels.par_chunks(w)).for_each(|(out_row, row)| smooth_row(row, window, out_row));
        let (pixels, rows) = (&*pixels, &*rows);
        out_chunk.par_chunks_mut(w * 4).enumerate().for_each(|(r, row)| {
            for (col, px) in row.chunks_exact_mut(4).enumerate() {
                let i = r * w + col;
                if let Some([re, im, m]) = smoothed_column(pixels, rows, i, h, w, window) {
                    let (re, im) = (px[0] + (re * inv) as f32, px[1] + (im * inv) as f32);
                    (px[0], px[1]) = (re, im);
                    px[2] = (px[2] + (m * inv) as f32).max(re.hypot(im) * (1.0 + 4.0 * f32::EPSILON));
                }
            }
        });
    }
}

/// Frames traced at once before their interreflection is averaged (`render_with`).
const SMOOTH_FRAMES: usize = 4;

/// What the averaging compares and averages of a pixel: its surface (plane and mean point,
/// f32: the tolerances are centimetres), its interreflection per unit of direct-light scale
/// with the phase of its own mean path taken out (re, im, magnitude), and the turn e^{ik·path}
/// and scale that give it back.
#[derive(Clone, Copy, Debug)]
struct Smoothable {
    normal: [f32; 3],
    offset: f32,
    point: [f32; 3],
    value: [f64; 3],
    turn: [f64; 2],
    scale: f64,
}

impl Smoothable {
    #[inline]
    fn same_surface(&self, o: &Smoothable) -> bool {
        let n = self.normal[0] * o.normal[0] + self.normal[1] * o.normal[1] + self.normal[2] * o.normal[2];
        let d = [self.point[0] - o.point[0], self.point[1] - o.point[1], self.point[2] - o.point[2]];
        n >= SAME_NORMAL as f32
            && (self.offset - o.offset).abs() <= SAME_PLANE as f32
            && d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= (SMOOTH_RADIUS * SMOOTH_RADIUS) as f32
    }
}

/// The interreflection of each pixel of one image row averaged over the pixels within
/// `window` columns that see the same surface (`Smoothable::same_surface`), per unit of
/// direct-light scale with each pixel's own path phase taken out. The first of the two passes of
/// an edge-aware average done separably, as image denoisers do (then `smoothed_column`).
/// Written here: the quantity averaged is particular to this renderer's light paths.
fn smooth_row(row: &[Option<Smoothable>], window: usize, out: &mut [[f64; 3]]) {
    for (pos, (me, o)) in row.iter().zip(out.iter_mut()).enumerate() {
        if let Some(me) = me {
            let lo = pos.saturating_sub(window);
            let hi = (pos + window).min(row.len() - 1);
            *o = mean_of_same(me, (lo..=hi).map(|q| (q == pos, row[q].as_ref(), row[q].map_or([0.0; 3], |p| p.value))));
        }
    }
}

/// Pixel i's interreflection (re, im, Σ|p|, summed over its sub-rays): the mean over the pixels
/// within `window` rows of i's column that see its surface of their row averages (`rows`),
/// turned back with i's own path phase and scale. None where i has nothing to average.
fn smoothed_column(pixels: &[Option<Smoothable>], rows: &[[f64; 3]], i: usize, h: usize, w: usize, window: usize) -> Option<[f64; 3]> {
    let me = pixels[i].as_ref()?;
    let per_frame = h * w;
    let (frame_start, within) = (i - i % per_frame, i % per_frame);
    let (col, pos) = (within % w, within / w);
    let (lo, hi) = (pos.saturating_sub(window), (pos + window).min(h - 1));
    let [er, ei, m] = mean_of_same(
        me,
        (lo..=hi).map(|q| {
            let j = frame_start + q * w + col;
            (q == pos, pixels[j].as_ref(), rows[j])
        }),
    );
    let [c, s] = me.turn;
    Some([me.scale * (er * c - ei * s), me.scale * (er * s + ei * c), me.scale * m])
}

/// The mean of the values of the candidates that are `me` itself or see its surface.
#[inline]
fn mean_of_same<'a>(me: &Smoothable, candidates: impl Iterator<Item = (bool, Option<&'a Smoothable>, [f64; 3])>) -> [f64; 3] {
    let (mut sum, mut n) = ([0.0; 3], 0.0);
    for (itself, other, v) in candidates {
        if itself || other.is_some_and(|o| me.same_surface(o)) {
            sum = [sum[0] + v[0], sum[1] + v[1], sum[2] + v[2]];
            n += 1.0;
        }
    }
    [sum[0] / n, sum[1] / n, sum[2] / n]
}

// --- small vector helpers ----------------------------------------------------------------

#[inline]
pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
}

#[inline]
pub(crate) fn add(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

#[inline]
pub(crate) fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

#[inline]
pub(crate) fn scale(a: [f64; 3], k: f64) -> [f64; 3] {
    [a[0] * k, a[1] * k, a[2] * k]
}

#[inline]
pub(crate) fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

/// Mirror image of the point p in the plane {x : n·x = d}, n unit.
#[inline]
pub(crate) fn reflect_point(p: [f64; 3], n: [f64; 3], d: f64) -> [f64; 3] {
    sub(p, scale(n, 2.0 * (dot(n, p) - d)))
}

/// Mirror direction v in a plane of unit normal n: v − 2(v·n)n.
#[inline]
fn reflect(v: [f64; 3], n: [f64; 3]) -> [f64; 3] {
    sub(v, scale(n, 2.0 * dot(v, n)))
}

#[inline]
pub(crate) fn rotate(m: &[[f64; 4]; 3], v: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

#[inline]
pub(crate) fn apply(m: &[[f64; 4]; 3], p: [f64; 3]) -> [f64; 3] {
    add(rotate(m, p), [m[0][3], m[1][3], m[2][3]])
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};
    use rand_pcg::Pcg64;

    fn matte_room(walls: &[Wall], blocks: &[Block], cell: f64) -> Scene {
        Scene::new(walls, blocks, vec![Material::matte(0.5)], 0, 0, 3.0, cell).unwrap()
    }

    fn wall(a: [f64; 2], b: [f64; 2]) -> Wall {
        Wall { a, b, bottom: 0.0, top: 3.0, material: 0 }
    }

    fn unit(v: [f64; 3]) -> [f64; 3] {
        scale(v, 1.0 / norm(v))
    }

    /// Nearest hit by testing every primitive: the reference for the grid walk.
    fn brute_force(scene: &Scene, o: [f64; 3], d: [f64; 3]) -> Option<f64> {
        let mut best = f64::INFINITY;
        for w in &scene.walls {
            if let Some(h) = hit_wall(w, o, d, T_MIN, best) {
                best = h.t;
            }
        }
        for b in &scene.blocks {
            if let Some(h) = hit_block(b, o, d, T_MIN, best) {
                best = h.t;
            }
        }
        for (z, dz) in [(0.0, d[2] < 0.0), (scene.ceiling_height, d[2] > 0.0)] {
            let t = (z - o[2]) / d[2];
            if dz && t > T_MIN && t < best {
                best = t;
            }
        }
        best.is_finite().then_some(best)
    }

    #[test]
    fn wall_hit_at_known_distance_with_facing_normal() {
        let scene = matte_room(&[wall([3.0, -5.0], [3.0, 5.0])], &[], 0.5);
        let d = unit([1.0, 0.0, 0.2]);
        let hit = scene.intersect([0.0, 0.0, 1.0], d, T_MIN, f64::INFINITY).unwrap();
        assert!((hit.t - 3.0 / d[0]).abs() < 1e-12);
        assert_eq!(hit.normal, [-1.0, 0.0, 0.0]);
    }

    #[test]
    fn wall_is_only_as_high_as_its_top() {
        let low = Wall { top: 1.0, ..wall([3.0, -5.0], [3.0, 5.0]) };
        let scene = matte_room(&[low], &[], 0.5);
        // Rising at 45°, the ray passes 3 m out at z = 3.5 > 1: it meets the ceiling instead.
        let hit = scene.intersect([0.0, 0.0, 0.5], unit([1.0, 0.0, 1.0]), T_MIN, f64::INFINITY).unwrap();
        assert_eq!(hit.normal, [0.0, 0.0, -1.0]);
        assert!((hit.t - 2.5 * 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn rotated_box_face_distance() {
        // A unit cube turned 45°: its corner points at the ray, 2 − √2/2 m away.
        let b = Block { centre: [2.0, 0.0], half: [0.5, 0.5], yaw: std::f64::consts::FRAC_PI_4, bottom: 0.0, top: 1.0, material: 0 };
        let scene = matte_room(&[], &[b], 0.5);
        let hit = scene.intersect([0.0, 0.0, 0.5], [1.0, 0.0, 0.0], T_MIN, f64::INFINITY).unwrap();
        assert!((hit.t - (2.0 - 0.5 * 2f64.sqrt())).abs() < 1e-12);
        assert!(hit.normal[0] < 0.0 && hit.normal[2] == 0.0);
        // From inside the box the ray meets the far face.
        let inside = scene.intersect([2.0, 0.0, 0.5], [1.0, 0.0, 0.0], T_MIN, f64::INFINITY).unwrap();
        assert!((inside.t - 0.5 * 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn grid_walk_matches_brute_force_on_random_rays() {
        let mut rng = Pcg64::seed_from_u64(5);
        let mut walls = vec![];
        for _ in 0..60 {
            let a: [f64; 2] = [rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0)];
            let len: f64 = rng.random_range(0.2..6.0);
            let ang: f64 = rng.random_range(0.0..std::f64::consts::TAU);
            // Every fourth wall lies exactly on cell boundaries, the hard case for binning.
            let (a, b) = if walls.len() % 4 == 0 {
                let a = [a[0].round() * 0.5, a[1].round() * 0.5];
                (a, [a[0] + len.round(), a[1]])
            } else {
                (a, [a[0] + len * ang.cos(), a[1] + len * ang.sin()])
            };
            if a != b {
                walls.push(Wall { a, b, bottom: 0.0, top: rng.random_range(0.3..3.0), material: 0 });
            }
        }
        let blocks: Vec<Block> = (0..15)
            .map(|_| Block {
                centre: [rng.random_range(-8.0..8.0), rng.random_range(-8.0..8.0)],
                half: [rng.random_range(0.1..1.0), rng.random_range(0.1..1.0)],
                yaw: rng.random_range(0.0..3.0),
                bottom: rng.random_range(0.0..0.8),
                top: rng.random_range(0.9..2.5),
                material: 0,
            })
            .collect();
        for cell in [0.25, 0.5, 1.3] {
            let scene = matte_room(&walls, &blocks, cell);
            for _ in 0..4000 {
                let o = [rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0), rng.random_range(0.05..2.9)];
                let d = unit([rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-0.4..0.4)]);
                let got = scene.intersect(o, d, T_MIN, f64::INFINITY).map(|h| h.t);
                let want = brute_force(&scene, o, d);
                assert_eq!(got.is_some(), want.is_some());
                // The shadow test agrees with the nearest hit for any segment length.
                let reach: f64 = rng.random_range(0.1..12.0);
                let shadowed = scene.occluded(o, d, T_MIN, reach, &mut Mailbox::for_scene(&scene));
                assert_eq!(shadowed, want.is_some_and(|w| w < reach));
                if let (Some(g), Some(w)) = (got, want) {
                    assert!((g - w).abs() < 1e-9, "cell {cell}: grid {g} vs brute force {w}");
                }
            }
        }
    }

    #[test]
    fn vertical_rays_and_rays_from_outside_the_grid() {
        let scene = matte_room(&[wall([0.0, 0.0], [4.0, 0.0])], &[], 0.5);
        let up = scene.intersect([1.0, 1.0, 0.5], [0.0, 0.0, 1.0], T_MIN, f64::INFINITY).unwrap();
        assert!((up.t - 2.5).abs() < 1e-12);
        // Starting far outside the grid, heading back in across its upper edge.
        let d = unit([0.0, -1.0, 0.0]);
        let hit = scene.intersect([2.0, 50.0, 1.0], d, T_MIN, f64::INFINITY).unwrap();
        assert!((hit.t - 50.0).abs() < 1e-9);
    }

    #[test]
    fn grid_bars_cover_the_stated_fraction() {
        let m = Material { kind: Kind::Grid, albedo: 0.4, specular: 0.0, transmission: 0.0, coverage: 0.35, pitch: 0.1 };
        let mut rng = Pcg64::seed_from_u64(2);
        let n = 200_000;
        let hits = (0..n)
            .filter(|_| m.on_bar([3.0, rng.random_range(-5.0..5.0), rng.random_range(0.0..3.0)], [-1.0, 0.0, 0.0]))
            .count();
        assert!((hits as f64 / n as f64 - 0.35).abs() < 0.005);
        // The same point seen from the other side lies on the same bar.
        for _ in 0..1000 {
            let p = [3.0, rng.random_range(-5.0..5.0), rng.random_range(0.0..3.0)];
            assert_eq!(m.on_bar(p, [-1.0, 0.0, 0.0]), m.on_bar(p, [1.0, 0.0, 0.0]));
        }
    }

    fn params() -> RenderParams {
        RenderParams {
            f_mod: 20e6,
            amplitude_at_1m: 1.0,
            max_bounces: 2,
            min_gain: 1e-6,
            illumination: None,
            multipath_rays: 0,
            multipath_window: 0,
            bounce: Illumination::coaxial(),
            seed: 0,
        }
    }

    fn trace_one(scene: &Scene, o: [f64; 3], d: [f64; 3]) -> Return {
        let mut acc = Return::default();
        let mut work = Workspace::for_scene(scene);
        trace(scene, &params(), &SubRay { origin: o, dir: d, path: 0.0, g2: 1.0, g1: 1.0 }, &mut acc, &mut work);
        acc
    }

    #[test]
    fn phasors_near_the_first_path_match_sin_cos() {
        // Phases within NEAR_PHASE of the first path go by the series, others by sin_cos: both
        // against sums of (cos, sin) computed here.
        let mut rng = Pcg64::seed_from_u64(3);
        for _ in 0..2000 {
            let mut acc = Return::default();
            let (mut re, mut im) = (0.0, 0.0);
            let p0: f64 = rng.random_range(-30.0..30.0);
            for _ in 0..6 {
                let phase = p0 + rng.random_range(-0.15..0.15);
                let amplitude: f64 = rng.random_range(0.0..2.0);
                acc.add(amplitude, phase);
                re += amplitude * phase.cos();
                im += amplitude * phase.sin();
            }
            assert!((acc.re - re).abs() < 1e-13 && (acc.im - im).abs() < 1e-13, "{} {re}", acc.re);
        }
    }

    #[test]
    fn matte_return_has_inverse_square_amplitude_and_round_trip_phase() {
        let scene = matte_room(&[wall([2.0, -5.0], [2.0, 5.0])], &[], 0.5);
        let acc = trace_one(&scene, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]);
        let amplitude = acc.re.hypot(acc.im);
        assert!((amplitude - 0.5 / 4.0).abs() < 1e-12);
        let phase = acc.im.atan2(acc.re).rem_euclid(std::f64::consts::TAU);
        let want = (4.0 * std::f64::consts::PI * 20e6 * 2.0 / SPEED_OF_LIGHT).rem_euclid(std::f64::consts::TAU);
        assert!((phase - want).abs() < 1e-12);
    }

    #[test]
    fn metal_returns_the_mirrored_world() {
        // A purely specular wall at x = 2 and a matte wall behind the camera at x = −3: the
        // reading is the unfolded path 2 + 5 = 7 m.
        let metal = Material { kind: Kind::Metal, albedo: 0.0, specular: 0.8, transmission: 0.0, coverage: 0.0, pitch: 1.0 };
        let walls = [
            Wall { material: 1, ..wall([2.0, -5.0], [2.0, 5.0]) },
            wall([-3.0, -5.0], [-3.0, 5.0]),
        ];
        let scene = Scene::new(&walls, &[], vec![Material::matte(0.5), metal], 0, 0, 3.0, 0.5).unwrap();
        let acc = trace_one(&scene, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]);
        assert!((acc.magnitude - 0.64 * 0.5 / 49.0).abs() < 1e-12);
        assert!((acc.ambient - 0.8 * 0.5).abs() < 1e-12);
    }

    #[test]
    fn glass_passes_most_light_to_the_wall_behind() {
        let glass = Material { kind: Kind::Glass, albedo: 0.0, specular: 0.0, transmission: 0.9, coverage: 0.0, pitch: 1.0 };
        let walls = [Wall { material: 1, ..wall([1.0, -5.0], [1.0, 5.0]) }, wall([3.0, -5.0], [3.0, 5.0])];
        let scene = Scene::new(&walls, &[], vec![Material::matte(0.5), glass], 0, 0, 3.0, 0.5).unwrap();
        let acc = trace_one(&scene, [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]);
        assert!((acc.magnitude - 0.81 * 0.5 / 9.0).abs() < 1e-12);
    }

    fn test_rig(h: usize, w: usize, s: usize) -> Rig {
        let mut rng = Pcg64::seed_from_u64(9);
        let dirs: Vec<[f64; 3]> = (0..h * w * s)
            .map(|_| [rng.random_range(-0.6..0.6), rng.random_range(-0.5..0.5), 1.0])
            .collect();
        // A four-sided 45° pyramid, apex 0.1 m above the lens.
        let c = std::f64::consts::FRAC_1_SQRT_2;
        let mirrors: Vec<Mirror> = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]
            .iter()
            .map(|e| {
                let normal = [-c * e[0], -c * e[1], c];
                let apex = [0.0, 0.0, 0.1];
                let side = [-e[1], e[0]];
                let corner = |k: f64| [0.3 * e[0] + k * 0.3 * side[0], 0.3 * e[1] + k * 0.3 * side[1], 0.4];
                Mirror { normal, d: 0.1 * c, polygon: vec![apex, corner(1.0), corner(-1.0)], reflectivity: 0.9 }
            })
            .collect();
        let mount = [[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.4]];
        Rig::new(&dirs, h, w, s, &mirrors, mount).unwrap()
    }

    #[test]
    fn reflected_rays_leave_from_the_mirror_plane() {
        let rig = test_rig(6, 7, 3);
        let reflected = rig.rays().iter().filter(|r| r.g2 < 1.0).count();
        assert!(reflected > 0);
        for r in rig.rays().iter().filter(|r| r.g2 < 1.0) {
            assert!((r.g2 - 0.81).abs() < 1e-12 && (norm(r.dir) - 1.0).abs() < 1e-12);
            assert!((norm(r.origin) - r.path).abs() < 1e-12);
        }
    }

    #[test]
    fn same_image_for_any_thread_count() {
        let rig = test_rig(12, 10, 4);
        let walls = [wall([-3.0, -3.0], [3.0, -3.0]), wall([3.0, -3.0], [3.0, 3.0]), wall([3.0, 3.0], [-3.0, 2.0])];
        let blocks = [Block { centre: [1.0, 1.0], half: [0.3, 0.4], yaw: 0.3, bottom: 0.0, top: 0.8, material: 0 }];
        let scene = matte_room(&walls, &blocks, 0.5);
        let poses = [[0.0, 0.0, 0.0], [0.5, -0.2, 1.0]];
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut out = vec![0f32; poses.len() * 12 * 10 * 4];
            pool.install(|| render(&scene, &rig, &params(), &poses, &mut out));
            out
        };
        let one = run(1);
        assert!(one.iter().any(|&v| v != 0.0));
        assert_eq!(one, run(2));
        assert_eq!(one, run(3));
    }

    #[test]
    fn leds_and_multipath_give_the_same_image_for_any_thread_count() {
        let rig = test_rig(12, 10, 4);
        let walls = [wall([-3.0, -3.0], [3.0, -3.0]), wall([3.0, -3.0], [3.0, 3.0]), wall([3.0, 3.0], [-3.0, 2.0])];
        let scene = matte_room(&walls, &[], 0.5);
        let leds = vec![[0.03, 0.0, 0.0], [0.0, 0.03, 0.0], [-0.03, 0.0, 0.0], [0.0, -0.03, 0.0]];
        let p = RenderParams {
            illumination: Some(Illumination { leds, profile_exponent: 3.6, min_cos: 0.6 }),
            multipath_rays: 6,
            multipath_window: 2,
            seed: 4,
            ..params()
        };
        let poses = [[0.0, 0.0, 0.0], [0.5, -0.2, 1.0]];
        let run = |threads: usize, p: &RenderParams| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let mut out = vec![0f32; poses.len() * 12 * 10 * 4];
            pool.install(|| render(&scene, &rig, p, &poses, &mut out));
            out
        };
        let one = run(1, &p);
        assert_eq!(one, run(2, &p));
        assert_eq!(one, run(3, &p));
        // Another seed draws other secondary rays.
        assert_ne!(one, run(2, &RenderParams { seed: 5, ..p.clone() }));
    }

    #[test]
    fn light_masks_cover_every_point_a_source_lights() {
        // Along each sub-ray (camera frame), points at many t, each facing the light: every
        // source that `paths` finds lighting a point has its bit, and the LEDs' direct light
        // reaches no point beyond `direct_reach`.
        let rig = test_rig(10, 10, 4);
        let scene = matte_room(&[wall([5.0, -5.0], [5.0, 5.0])], &[], 1.0);
        let mut mail = Mailbox::for_scene(&scene);
        let identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]];
        let leds = vec![[0.035, 0.0, 0.0], [0.0, 0.035, 0.0], [-0.035, 0.0, 0.0], [0.0, -0.035, 0.0]];
        let (mut lit, mut direct_lit) = (0, 0);
        for min_cos in [0.766, 0.3, 0.95] {
            let light = Illumination { leds: leds.clone(), profile_exponent: 1.0, min_cos };
            let masks = crate::light::candidate_masks(&light, &rig.mirrors, &rig.rays);
            let camera = PoseLight::new(&light, &rig.mirrors, &identity);
            let direct = camera.direct_bits();
            for (ray, mask) in rig.rays.iter().zip(&masks).filter(|(r, _)| r.g2 > 0.0) {
                for k in 0..400 {
                    let t = 1e-4 * 1.04f64.powi(k); // 0.1 mm to about 70 m
                    let x = add(ray.origin, scale(ray.dir, t));
                    for bit in 0..20 {
                        // A normal facing the source's side: the point is lit if anything lights it.
                        let mut found = false;
                        for n in [scale(ray.dir, -1.0), [0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0]] {
                            camera.paths(&scene, x, n, 1u64 << bit, false, &mut mail, |_, _| found = true);
                        }
                        if found {
                            lit += 1;
                            assert!(mask.candidates & (1 << bit) != 0, "source {bit} lights t = {t} but is masked out");
                            if direct & (1 << bit) != 0 {
                                direct_lit += 1;
                                assert!(t <= mask.direct_reach, "direct light at t = {t} beyond {}", mask.direct_reach);
                            }
                        }
                    }
                }
            }
        }
        assert!(lit > 10_000 && direct_lit > 100, "{lit} lit, {direct_lit} by the LEDs directly");
    }

    #[test]
    fn light_masks_skip_only_sources_that_light_nothing() {
        // The same image with the rig's candidate masks as with every source tested, and the
        // masks do leave sources out (else the test would prove nothing).
        let rig = test_rig(16, 12, 4);
        let walls = [wall([-3.0, -3.0], [3.0, -3.0]), wall([3.0, -3.0], [3.0, 3.0]), wall([3.0, 3.0], [-3.0, 2.0]), wall([-3.0, 2.0], [-3.0, -3.0])];
        let scene = matte_room(&walls, &[], 0.5);
        for (exponent, min_cos) in [(1.0, 0.766), (0.0, -1.0), (3.6, 0.2)] {
            let leds = vec![[0.035, 0.0, 0.0], [0.0, 0.035, 0.0], [-0.035, 0.0, 0.0], [0.0, -0.035, 0.0]];
            let p = RenderParams {
                illumination: Some(Illumination { leds, profile_exponent: exponent, min_cos }),
                multipath_rays: 2,
                ..params()
            };
            let masks = light_masks(&rig, &p).unwrap();
            let poses = [[0.0, 0.0, 0.0], [0.4, -0.3, 2.0]];
            let image = |masks: Option<&[SubRayLight]>| {
                let mut out = vec![0f32; poses.len() * 16 * 12 * 4];
                render_with(&scene, &rig, &p, masks, &poses, &poses, &mut out);
                out
            };
            let with = image(Some(&masks));
            // The LEDs light most pixels (Σ|p| > 0), so the light paths are exercised.
            let lit = with.chunks_exact(4).filter(|px| px[2] > 0.0).count();
            assert!(lit * 2 > poses.len() * 16 * 12, "{lit} lit pixels");
            assert_eq!(with, image(None), "exponent {exponent}, min_cos {min_cos}");
            let sources = 4 * (1 + rig.mirrors.len());
            // Over the sub-rays that exist (the others test nothing anyway): fewer than half.
            let live: Vec<u64> = masks.iter().zip(&rig.rays).filter(|(_, r)| r.g2 > 0.0).map(|(m, _)| m.candidates).collect();
            let tested: u32 = live.iter().map(|m| (m & ((1u64 << sources) - 1)).count_ones()).sum();
            assert!(!live.is_empty() && (tested as usize) < live.len() * sources / 2, "{tested} of {}", live.len() * sources);
        }
    }
    #[test]
    fn smoothing_averages_the_interreflection_relative_to_each_pixels_own_path() {
        // One image column (w = 1) of pixels on the wall x = 3 (normal −x) at paths 3.00–3.35 m,
        // each pixel's interreflection E_i·e^{ik·path_i} (times its scale), and one pixel on the
        // floor among them. Averaged over the wall's pixels within the window, relative to each
        // one's own path: with one E for all, every pixel gets its own back; with E_i apart, the
        // mean of the E_i in its window, turned by its own path; the floor pixel stays alone.
        let k = 4.0 * std::f64::consts::PI * 20e6 / SPEED_OF_LIGHT;
        let pixel = |path: f64, z: f64, normal: [f64; 3], e: [f64; 2], w: f64| {
            let mut ind = Indirect::default();
            ind.sent_from(w, path, [3.0, 0.1, z], normal);
            let (s, c) = (k * path).sin_cos();
            (ind.re, ind.im, ind.magnitude) = (w * (e[0] * c - e[1] * s), w * (e[0] * s + e[1] * c), w * 0.7);
            ind
        };
        let (wall, floor) = ([-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]);
        for spread in [0.0, 0.2] {
            let e_of = |i: usize| [0.3 + spread * (i as f64 - 3.0), -0.2];
            let path_of = |i: usize| 3.0 + 0.05 * i as f64;
            let column: Vec<Indirect> = (0..8)
                .map(|i| {
                    if i == 5 {
                        pixel(path_of(i), 0.0, floor, [1.0, 1.0], 2.0)
                    } else {
                        pixel(path_of(i), 1.0 + 0.02 * i as f64, wall, e_of(i), 1.5)
                    }
                })
                .collect();
            let pixels: Vec<Option<Smoothable>> = column.iter().map(|ind| ind.smoothable(k)).collect();
            // w = 1: each row average is the pixel itself.
            let rows: Vec<[f64; 3]> = pixels.iter().map(|p| p.unwrap().value).collect();
            for (i, ind) in column.iter().enumerate() {
                let got = smoothed_column(&pixels, &rows, i, 8, 1, 2).unwrap();
                let want = if i == 5 {
                    [ind.re, ind.im, ind.magnitude]
                } else {
                    let near: Vec<usize> = (i.saturating_sub(2)..=(i + 2).min(7)).filter(|&j| j != 5).collect();
                    let mean = near.iter().map(|&j| e_of(j)[0]).sum::<f64>() / near.len() as f64;
                    let (s, c) = (k * path_of(i)).sin_cos();
                    [1.5 * (mean * c + 0.2 * s), 1.5 * (mean * s - 0.2 * c), 1.5 * 0.7]
                };
                for (g, w) in got.iter().zip(&want) {
                    assert!((g - w).abs() < 1e-12, "spread {spread}, pixel {i}: {got:?} vs {want:?}");
                }
            }
        }
    }
}
