//! The state obvhs's `traverse!` macro walks a CWBVH with, owned here so
//! that starting a query costs nothing beyond its few words.
//!
//! obvhs's own `Traversal` holds its node stack as a zeroed array of 32
//! entries: 256 bytes written before every query. In the Cornell box,
//! where a query visits 1.4 nodes and pushes next to nothing, not writing
//! them took the render from 1,108.0 M to 1,094.2 M instructions
//! (callgrind, 2 spp, one thread: about 18 of a query's 700). This state leaves the stack
//! uninitialised; the macro pushes before it pops (it pops only when the
//! stack is not empty), so nothing unwritten is ever read. Its fields
//! carry the names and meanings the macro expects; the traversal it
//! drives is obvhs's, node for node.

use glam::{UVec2, Vec3A};
use obvhs::faststack::FastStack;
use std::mem::MaybeUninit;

/// Entries the node stack holds: obvhs's `TRAVERSAL_STACK_SIZE`, which
/// its CWBVH validation keeps above the tree's depth.
const STACK: usize = 32;

/// The room a node stack keeps its entries in: a local of the query,
/// created without writing anything ([`slots`]).
pub(crate) type Slots = [MaybeUninit<UVec2>; STACK];

/// Room for a node stack, uninitialised.
#[inline(always)]
pub(crate) const fn slots() -> Slots {
    [const { MaybeUninit::uninit() }; STACK]
}

/// A node stack whose slots are written before they are read. It borrows
/// its room rather than holding it: held, the 256 bytes moved with the
/// state when [`Walk::new`] returned it, and that copy wrote them all
/// before every query after all (callgrind: 81 instructions and 42 writes
/// a query, 6.4% of tracing the room's incoherent rays).
pub(crate) struct NodeStack<'a> {
    data: &'a mut Slots,
    index: usize,
}

impl FastStack<UVec2> for NodeStack<'_> {
    /// As obvhs's stack: a full stack overwrites its last entry (a tree
    /// that deep fails obvhs's validation before it is ever traced).
    #[inline(always)]
    fn push(&mut self, v: UVec2) {
        // SAFETY: `index` stays below STACK (the `min` below).
        unsafe { self.data.get_unchecked_mut(self.index) }.write(v);
        self.index = (self.index + 1).min(STACK - 1);
    }

    /// The traversal pops only a stack it has checked is not empty, so
    /// the entry read was pushed.
    #[inline(always)]
    fn pop_fast(&mut self) -> UVec2 {
        debug_assert!(self.index > 0, "pop of an empty node stack");
        self.index = self.index.saturating_sub(1);
        // SAFETY: `index` is below STACK, and every slot below the top
        // was written by `push` before (see above).
        unsafe { self.data.get_unchecked(self.index).assume_init() }
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<UVec2> {
        if self.index == 0 {
            None
        } else {
            Some(self.pop_fast())
        }
    }

    #[inline(always)]
    fn len(&self) -> usize {
        self.index
    }

    #[inline(always)]
    fn is_empty(&self) -> bool {
        self.index == 0
    }

    #[inline(always)]
    fn clear(&mut self) {
        self.index = 0;
    }
}

/// What `obvhs::traverse!` reads and writes as it walks: obvhs's
/// `Traversal` less its direction, with [`NodeStack`].
pub(crate) struct Walk<'a> {
    pub stack: NodeStack<'a>,
    pub current_group: UVec2,
    pub primitive_group: UVec2,
    pub oct_inv4: u32,
    pub primitive_id: u32,
    pub hitmask: u32,
}

impl<'a> Walk<'a> {
    /// At the root of a BVH with `nodes` nodes, for a ray along `dir`
    /// (obvhs's `CwBvh::new_traversal`), its stack kept in `room`.
    #[inline(always)]
    pub fn new(nodes: usize, dir: Vec3A, room: &'a mut Slots) -> Self {
        Self {
            stack: NodeStack {
                data: room,
                index: 0,
            },
            current_group: if nodes == 0 {
                UVec2::ZERO
            } else {
                UVec2::new(0, 0x8000_0000)
            },
            primitive_group: UVec2::ZERO,
            oct_inv4: octant_inv4(dir),
            primitive_id: 0,
            hitmask: 0,
        }
    }
}

/// The ray's octant, inverted, in each byte (obvhs's
/// `ray_get_octant_inv4`): which child order the node test reports in.
#[inline(always)]
fn octant_inv4(dir: Vec3A) -> u32 {
    (if dir.x < 0.0 { 0 } else { 0x0404_0404 })
        | (if dir.y < 0.0 { 0 } else { 0x0202_0202 })
        | (if dir.z < 0.0 { 0 } else { 0x0101_0101 })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The state starts where obvhs's does, for rays of every octant, at
    /// the root of a built BVH and of an empty one.
    #[test]
    fn starts_as_obvhs_traversal_does() {
        let tris = super::super::tests::soup(50, 2);
        let ids: Vec<u32> = (0..tris.len() as u32).collect();
        let built = super::super::Accel::build(&tris, &ids, 20.0).bvh;
        let empty = obvhs::cwbvh::CwBvh::default();
        for i in 0..27 {
            let c = |k: i32| [-1.0, 0.0, 1.0][((i / 3i32.pow(k as u32)) % 3) as usize];
            let dir = Vec3A::new(c(0), c(1), c(2));
            for bvh in [&built, &empty] {
                let theirs = bvh.new_traversal(dir);
                let mut room = slots();
                let ours = Walk::new(bvh.nodes.len(), dir, &mut room);
                assert_eq!(ours.oct_inv4, theirs.oct_inv4, "{dir:?}");
                assert_eq!(ours.current_group, theirs.current_group, "{dir:?}");
                assert_eq!(ours.primitive_group, theirs.primitive_group);
                assert_eq!(
                    (ours.primitive_id, ours.hitmask),
                    (theirs.primitive_id, theirs.hitmask)
                );
                assert!(ours.stack.is_empty());
            }
        }
        assert!(!built.nodes.is_empty());
    }

    /// Pushes and pops as obvhs's stack does, entry for entry, through
    /// runs that fill it and keep pushing (a full stack overwrites its
    /// top).
    #[test]
    fn a_stack_pops_what_obvhs_stack_pops() {
        use obvhs::faststack::StackStack;
        let mut room = slots();
        let mut ours = Walk::new(1, Vec3A::X, &mut room).stack;
        let mut theirs = StackStack::<UVec2, STACK>::default();
        for (round, pushes) in [3u32, 10, 31, 32, 40].into_iter().enumerate() {
            for k in 0..pushes {
                let v = UVec2::new(k, round as u32);
                ours.push(v);
                theirs.push(v);
            }
            assert_eq!(ours.len(), theirs.len(), "round {round}");
            while !theirs.is_empty() {
                assert_eq!(ours.pop(), theirs.pop(), "round {round}");
            }
            assert!(ours.is_empty() && ours.pop().is_none());
        }
        ours.push(UVec2::ONE);
        ours.clear();
        assert!(ours.is_empty());
    }
}
