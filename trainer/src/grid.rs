//! The trainer's one spatial grid: a uniform hash grid in f64 that files items (points,
//! or boxes such as triangles' bounds) by index under the integer cells
//! `floor(p / cell)` they touch, and answers which items are filed in one cell or in
//! the cube of cells around a point. The cloth collider, the garments' skinning
//! binding and the mesh self-intersection check use it.
//!
//! Invariants the users rely on: cells are absolute (no origin) and every cell is one
//! `cell` wide, so a point's cell contains it and the cells within `ring` of it cover
//! everything within `ring * cell` of it; a box is filed in every cell it overlaps, so
//! a point inside a box finds it in its own cell; each cell lists its items in the
//! order they were filed, so queries that keep the first of equal results (the
//! collider's closest triangle) are deterministic.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::DVec3;

/// Integer cell coordinates.
pub type Cell = [i64; 3];

/// A uniform spatial hash grid of item indices.
#[derive(Clone, Debug)]
pub struct Grid {
    cell: f64,
    cells: HashMap<Cell, Vec<u32>, BuildHasherDefault<CellHasher>>,
}

/// A multiply-rotate hash of a cell's three coordinates: the cloth collider looks up a
/// cell per vertex per substep, where SipHash's resistance to chosen keys buys nothing
/// (the keys are positions) and costs a few percent of a simulation. Queries do not
/// depend on the hash: each cell keeps its items in filing order, and [`Grid::cells`]
/// sorts the keys.
#[derive(Clone, Copy, Debug, Default)]
pub struct CellHasher(u64);

impl Hasher for CellHasher {
    fn write(&mut self, bytes: &[u8]) {
        for chunk in bytes.chunks(8) {
            let mut word = [0u8; 8];
            word[..chunk.len()].copy_from_slice(chunk);
            self.write_u64(u64::from_le_bytes(word));
        }
    }

    fn write_i64(&mut self, i: i64) {
        self.write_u64(i as u64);
    }

    fn write_u64(&mut self, i: u64) {
        // FxHash's step: rotate, mix in the word, multiply by an odd constant.
        self.0 = (self.0.rotate_left(5) ^ i).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn finish(&self) -> u64 {
        self.0
    }
}

/// The axis-aligned bounds (min, max) of `points`; (`DVec3::MAX`, `DVec3::MIN`) for none.
pub fn bounds(points: impl IntoIterator<Item = DVec3>) -> (DVec3, DVec3) {
    points
        .into_iter()
        .fold((DVec3::MAX, DVec3::MIN), |(lo, hi), p| {
            (lo.min(p), hi.max(p))
        })
}

impl Grid {
    /// Point `i` filed in the cell that contains it.
    pub fn of_points(points: &[DVec3], cell: f64) -> Self {
        let mut grid = Self {
            cell,
            cells: HashMap::default(),
        };
        for (i, &p) in points.iter().enumerate() {
            grid.cells
                .entry(grid.cell_of(p))
                .or_default()
                .push(i as u32);
        }
        grid
    }

    /// Box `i` (min, max) grown by `reach` on every side, filed in every cell it
    /// overlaps: a point within `reach` of the box finds it in the point's own cell.
    pub fn of_boxes(
        boxes: impl IntoIterator<Item = (DVec3, DVec3)>,
        cell: f64,
        reach: f64,
    ) -> Self {
        let mut grid = Self {
            cell,
            cells: HashMap::default(),
        };
        for (i, (lo, hi)) in boxes.into_iter().enumerate() {
            let a = grid.cell_of(lo - reach);
            let b = grid.cell_of(hi + reach);
            for x in a[0]..=b[0] {
                for y in a[1]..=b[1] {
                    for z in a[2]..=b[2] {
                        grid.cells.entry([x, y, z]).or_default().push(i as u32);
                    }
                }
            }
        }
        grid
    }

    /// The cell size.
    pub fn cell_size(&self) -> f64 {
        self.cell
    }

    /// The cell that contains `p`.
    pub fn cell_of(&self, p: DVec3) -> Cell {
        let c = (p / self.cell).floor();
        [c.x as i64, c.y as i64, c.z as i64]
    }

    /// The items filed in `p`'s cell.
    pub fn at(&self, p: DVec3) -> &[u32] {
        self.cells.get(&self.cell_of(p)).map_or(&[], Vec::as_slice)
    }

    /// The items filed in the cells within `ring` cells of `p`'s (a cube of
    /// `2 ring + 1` cells a side), cell by cell; they include every point within
    /// `ring * cell` of `p`. A box filed in several of these cells comes once per cell.
    pub fn around(&self, p: DVec3, ring: i64) -> impl Iterator<Item = u32> + '_ {
        let c = self.cell_of(p);
        (-ring..=ring)
            .flat_map(move |dx| {
                (-ring..=ring).flat_map(move |dy| {
                    (-ring..=ring).map(move |dz| [c[0] + dx, c[1] + dy, c[2] + dz])
                })
            })
            .filter_map(|k| self.cells.get(&k))
            .flatten()
            .copied()
    }

    /// Every non-empty cell's items, cells in ascending order of their coordinates (so
    /// that a search that stops early stops at the same place every run).
    pub fn cells(&self) -> impl Iterator<Item = &[u32]> + '_ {
        let mut keys: Vec<&Cell> = self.cells.keys().collect();
        keys.sort_unstable();
        keys.into_iter().map(|k| self.cells[k].as_slice())
    }
}

#[cfg(test)]
mod tests {
    use rand::{Rng, SeedableRng};

    use super::*;

    fn random_points(n: usize, seed: u64) -> Vec<DVec3> {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        // Both signs: the cells either side of 0 are where a truncating cell goes wrong.
        (0..n)
            .map(|_| DVec3::from_array([0, 1, 2].map(|_| rng.random_range(-1.0..1.0))))
            .collect()
    }

    /// The distance from `p` to the box (0 inside).
    fn box_distance(p: DVec3, (lo, hi): (DVec3, DVec3)) -> f64 {
        (lo - p).max(p - hi).max(DVec3::ZERO).length()
    }

    #[test]
    fn around_finds_exactly_the_points_within_reach() {
        let points = random_points(2000, 7);
        let queries = random_points(300, 8);
        for (cell, ring) in [(0.1, 1), (0.07, 2), (0.25, 0)] {
            let grid = Grid::of_points(&points, cell);
            let reach = ring as f64 * cell;
            for &q in &queries {
                let mut found: Vec<u32> = grid.around(q, ring).collect();
                let n = found.len();
                found.sort_unstable();
                found.dedup();
                assert_eq!(found.len(), n, "a point filed twice");
                let within: Vec<u32> = found
                    .into_iter()
                    .filter(|&i| (points[i as usize] - q).length() <= reach)
                    .collect();
                let brute: Vec<u32> = (0..points.len() as u32)
                    .filter(|&i| (points[i as usize] - q).length() <= reach)
                    .collect();
                assert_eq!(within, brute, "query {q:?}, cell {cell}, ring {ring}");
            }
        }
    }

    #[test]
    fn at_finds_every_box_within_reach() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(9);
        // Triangle-sized boxes, some wider than a cell.
        let boxes: Vec<(DVec3, DVec3)> = random_points(500, 10)
            .into_iter()
            .map(|lo| {
                let size = DVec3::from_array([0, 1, 2].map(|_| rng.random_range(0.0..0.12)));
                (lo, lo + size)
            })
            .collect();
        let (cell, reach) = (0.03, 0.02);
        let grid = Grid::of_boxes(boxes.iter().copied(), cell, reach);
        // Half the queries in or just around a box, so that many are within reach.
        let queries = boxes
            .iter()
            .map(|&(lo, hi)| {
                DVec3::from_array(std::array::from_fn(|k| {
                    rng.random_range(lo[k] - reach..hi[k] + reach)
                }))
            })
            .chain(random_points(500, 11));
        let mut near = 0;
        for q in queries {
            let found = grid.at(q);
            for (i, &b) in boxes.iter().enumerate() {
                if box_distance(q, b) <= reach {
                    near += 1;
                    assert!(
                        found.contains(&(i as u32)),
                        "box {i} {b:?} is within {reach} of {q:?} but not in its cell"
                    );
                }
            }
            // Filed in order, once per cell.
            assert!(found.windows(2).all(|w| w[0] < w[1]), "{found:?}");
        }
        assert!(
            near > 300,
            "only {near} query-box pairs within reach: the test checks little"
        );
    }

    #[test]
    fn bounds_and_cells() {
        let (lo, hi) = bounds([
            DVec3::new(0.5, -1.0, 2.0),
            DVec3::new(-0.5, 3.0, 2.5),
            DVec3::new(0.0, 0.0, -4.0),
        ]);
        assert_eq!(
            (lo, hi),
            (DVec3::new(-0.5, -1.0, -4.0), DVec3::new(0.5, 3.0, 2.5))
        );
        let grid = Grid::of_points(
            &[DVec3::new(-0.05, 0.05, 0.0), DVec3::new(0.05, 0.05, 0.0)],
            0.1,
        );
        // -0.05 is in cell -1 (floor, not truncation).
        assert_eq!(grid.cell_of(DVec3::new(-0.05, 0.05, 0.0)), [-1, 0, 0]);
        assert_eq!(grid.at(DVec3::new(-0.01, 0.09, 0.09)), &[0]);
        let cells: Vec<&[u32]> = grid.cells().collect();
        assert_eq!(cells, [&[0u32][..], &[1][..]]);
    }
}
