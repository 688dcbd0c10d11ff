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

/// Which cameras of a multi-camera (ZJU-MoCap layout) sequence train and which are
/// held out. A camera in neither list is not loaded.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CameraSplit {
    pub train: Vec<usize>,
    /// None: every camera that does not train is held out.
    pub test: Option<Vec<usize>>,
}

impl From<usize> for CameraSplit {
    /// One training camera, every other held out (ZJU-MoCap's protocol).
    fn from(train_camera: usize) -> Self {
        Self {
            train: vec![train_camera],
            test: None,
        }
    }
}

impl CameraSplit {
    /// Each of `cameras` cameras' part (None: not loaded), or what is wrong with the
    /// split (a camera that does not exist, named twice, or both training and held out).
    pub fn splits(&self, cameras: usize) -> Result<Vec<Option<Split>>, String> {
        if self.train.is_empty() {
            return Err("no training camera".into());
        }
        let mut out = vec![None; cameras];
        let held_out = match &self.test {
            Some(t) => t.clone(),
            None => (0..cameras).filter(|c| !self.train.contains(c)).collect(),
        };
        for (list, part) in [(&self.train, Split::Train), (&held_out, Split::Test)] {
            for &c in list {
                let Some(slot) = out.get_mut(c) else {
                    return Err(format!(
                        "camera {c} does not exist ({cameras} cameras: 0 to {})",
                        cameras.saturating_sub(1)
                    ));
                };
                if let Some(was) = *slot {
                    return Err(if was == part {
                        format!("camera {c} is named twice")
                    } else {
                        format!("camera {c} both trains and is held out")
                    });
                }
                *slot = Some(part);
            }
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn camera_splits() {
        use Split::{Test, Train};
        assert_eq!(
            CameraSplit::from(1).splits(3),
            Ok(vec![Some(Test), Some(Train), Some(Test)])
        );
        let three = CameraSplit {
            train: vec![0, 1, 2],
            test: Some(vec![3]),
        };
        assert_eq!(
            three.splits(5),
            Ok(vec![
                Some(Train),
                Some(Train),
                Some(Train),
                Some(Test),
                None
            ])
        );
        assert!(three
            .splits(3)
            .unwrap_err()
            .contains("camera 3 does not exist"));
        let both = CameraSplit {
            train: vec![0, 1],
            test: Some(vec![1]),
        };
        assert!(both
            .splits(2)
            .unwrap_err()
            .contains("both trains and is held out"));
        let twice = CameraSplit {
            train: vec![0, 0],
            test: None,
        };
        assert!(twice.splits(2).unwrap_err().contains("named twice"));
    }
}
