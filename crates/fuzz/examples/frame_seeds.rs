//! Writes seed inputs for the `frames` target: one encoded message of each
//! family and most variants, into the directory given (fuzz/corpus/frames).

use locus_protocol::control::{
    Opening, PassSamples, Registration, SchedulerToWorker, TileAssignment, TileResult,
    WorkerToScheduler,
};
use locus_protocol::handshake::Handshake;
use locus_protocol::rays::PeerMsg;
use locus_protocol::submit::{SchedulerToClient, TrianglePart};

fn main() {
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("usage: frame_seeds DIR"));
    std::fs::create_dir_all(&dir).unwrap();
    let mut n = 0;
    let mut put = |bytes: Vec<u8>| {
        std::fs::write(dir.join(format!("seed-{n:02}")), bytes).unwrap();
        n += 1;
    };
    let tile = TileAssignment {
        job: 3,
        tile: 7,
        pass: 1,
        samples: PassSamples::Even([1, 2]),
        x0: 0,
        y0: 0,
        x1: 4,
        y1: 4,
        queue_share: 1 << 20,
    };
    put(postcard::to_allocvec(&Handshake::Hello {
        version: 9,
        nonce: [7; 32],
    })
    .unwrap());
    put(postcard::to_allocvec(&Handshake::Refused {
        reason: "no".into(),
    })
    .unwrap());
    put(postcard::to_allocvec(&Opening::Register(Registration {
        listen: "a:1".into(),
        cores: 2,
        memory_budget: 1 << 30,
        resident: 1 << 20,
        name: "w".into(),
        layouts: true,
    }))
    .unwrap());
    put(postcard::to_allocvec(&Opening::Attach { job: 4 }).unwrap());
    put(postcard::to_allocvec(&TrianglePart {
        tris: vec![[glam::Vec3::ONE; 3]; 2],
        material: vec![0, 1],
        normals: vec![[glam::Vec3::Z; 3]; 2],
    })
    .unwrap());
    put(postcard::to_allocvec(&SchedulerToWorker::Tile(tile.clone())).unwrap());
    put(postcard::to_allocvec(&SchedulerToWorker::NoMoreTiles { job: 3 }).unwrap());
    put(
        postcard::to_allocvec(&WorkerToScheduler::TileDone(TileResult {
            job: 3,
            tile: 7,
            pass: 1,
            sums: vec![
                locus_core::passes::Moments {
                    sum: [0.5, 1.0, 2.0],
                    squares: [0.25, 1.0, 4.0],
                };
                4
            ],
        }))
        .unwrap(),
    );
    put(postcard::to_allocvec(&WorkerToScheduler::NeedTiles { job: 3, count: 4 }).unwrap());
    put(postcard::to_allocvec(&SchedulerToClient::Progress {
        job: 3,
        samples_done: 10,
        samples: 100,
        pass: 1,
        passes: 4,
    })
    .unwrap());
    put(postcard::to_allocvec(&SchedulerToClient::Pixels {
        job: 3,
        offset: 0,
        pixels: vec![[1.0; 3]; 3],
    })
    .unwrap());
    put(postcard::to_allocvec(&SchedulerToClient::Counts {
        job: 3,
        offset: 0,
        counts: vec![8, 0, 40],
    })
    .unwrap());
    put(
        postcard::to_allocvec(&SchedulerToWorker::Tile(TileAssignment {
            samples: PassSamples::Spread {
                first: vec![8; 16],
                count: (0..16).collect(),
            },
            ..tile.clone()
        }))
        .unwrap(),
    );
    put(postcard::to_allocvec(&PeerMsg::Hello { job: 3, from: 1 }).unwrap());
    put(postcard::to_allocvec(&PeerMsg::Fetch(vec![1, 2, 3])).unwrap());
    println!("{n} seeds in {}", dir.display());
}
