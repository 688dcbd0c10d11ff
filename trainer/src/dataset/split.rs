//! The split protocols: NeuMan's (every 5th frame from offset 2 held out for testing,
//! as HUGS evaluates) and the paper's 80/10/10; ZJU-MoCap's (one training camera, the
//! others for testing).

/// Which part of a dataset a frame or view belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    Train,
    Val,
    Test,
}

/// NeuMan as HUGS evaluates it: frames 2, 7, 12, ... are test, the rest train.
pub fn neuman_every_fifth(frames: usize) -> Vec<Split> {
    (0..frames)
        .map(|i| {
            if i % 5 == 2 {
                Split::Test
            } else {
                Split::Train
            }
        })
        .collect()
}

/// The paper's 80/10/10 split in time order: the first 80% train, the next 10%
/// validation, the last 10% test (at least one frame each when there are 3 or more).
pub fn neuman_80_10_10(frames: usize) -> Vec<Split> {
    let mut val = (frames as f64 * 0.1).round() as usize;
    let mut test = (frames as f64 * 0.1).round() as usize;
    if frames >= 3 {
        val = val.max(1);
        test = test.max(1);
    }
    let train = frames.saturating_sub(val + test);
    (0..frames)
        .map(|i| {
            if i < train {
                Split::Train
            } else if i < train + val {
                Split::Val
            } else {
                Split::Test
            }
        })
        .collect()
}

/// ZJU-MoCap: `train_camera` trains, every other camera tests.
pub fn zju_by_camera(cameras: usize, train_camera: usize) -> Vec<Split> {
    (0..cameras)
        .map(|c| {
            if c == train_camera {
                Split::Train
            } else {
                Split::Test
            }
        })
        .collect()
}
