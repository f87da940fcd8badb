//! Checkpoints: model, optimizer, schedule position and stream position, saved
//! atomically.
//!
//! A checkpoint is a directory `step-NNNNNNNN/` holding `model.bpk` and `optim.bpk`
//! (burnpack) and `state.json`. It is written under a temporary name, every file is
//! synced, then the directory is renamed into place and the `latest` file (the name of
//! the newest checkpoint) is replaced by a rename as well. A crash at any point leaves
//! `latest` naming a complete checkpoint.

use crate::error::TrainerError;
use crate::stream::StreamPosition;
use crate::subscribe::ResumeAt;
use burn::store::ModuleRecord;
use burn::tensor::Bytes;
use serde::{Deserialize, Serialize};
use std::fs::{self, File};
use std::io::Write as _;
use std::path::{Path, PathBuf};

/// Where the whole job (every rank of every host) stands in the pipeline's stream:
/// what a job of any size resumes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct JobPosition {
    /// The epoch of the job's next batch (of its slowest rank).
    pub epoch: u64,
    /// Samples of that epoch the whole job has consumed: the epoch's first ones in its
    /// order (the pipeline's `--start-sample`).
    pub samples: u64,
    /// Samples per step of the job (batch size × ranks of every host) when it saved.
    pub global_batch: u64,
}

impl JobPosition {
    /// The resume request's position: after these samples of the epoch.
    pub fn resume_at(self) -> ResumeAt {
        ResumeAt::Sample {
            epoch: self.epoch,
            sample: self.samples,
            global_batch: self.global_batch,
        }
    }
}

/// Everything besides the tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckpointState {
    /// Format tag.
    pub format: String,
    /// Optimizer steps taken.
    pub step: u64,
    /// Stream position of the next batch to train on.
    pub next_epoch: u64,
    /// See `next_epoch`.
    pub next_batch: u64,
    /// Data-parallel jobs (`--ddp`): the next (epoch, batch) of every rank's shard
    /// stream, by rank (they differ when shards end an epoch at different steps).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub ranks: Vec<[u64; 2]>,
    /// Where the whole job stands, in samples (absent when the pipeline did not say how
    /// its stream is scheduled, and in checkpoints of earlier versions): a job resumes
    /// from it on any number of ranks and hosts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job: Option<JobPosition>,
    /// Run name of the stream.
    pub run: String,
    /// The configuration the run was started with (as TOML).
    pub config: String,
    /// Learning rate of the last step.
    pub lr: f64,
    /// Loss of the last step.
    pub loss: f64,
}

impl CheckpointState {
    /// The stream position of the next batch to train on.
    pub fn next(&self) -> StreamPosition {
        StreamPosition::new(self.next_epoch, self.next_batch)
    }

    /// Where this rank's stream continues: after the job's samples when the checkpoint
    /// counted them (any job size), else at this rank's saved position `at` (a job of
    /// the same size only: the pipeline refuses it from a job of another size).
    pub fn resume_at(&self, at: StreamPosition) -> ResumeAt {
        match self.job {
            Some(job) => job.resume_at(),
            None => ResumeAt::Step {
                epoch: at.epoch,
                step: at.batch,
            },
        }
    }
}

/// The format tag of [`CheckpointState`].
pub const FORMAT: &str = "superflow.checkpoint/1";

/// A saved checkpoint's files.
#[derive(Debug, Clone)]
pub struct Checkpoint {
    /// Its directory.
    pub dir: PathBuf,
    /// Its state.
    pub state: CheckpointState,
}

impl Checkpoint {
    /// The model record file.
    pub fn model_path(&self) -> PathBuf {
        self.dir.join("model.bpk")
    }

    /// The optimizer record file.
    pub fn optim_path(&self) -> PathBuf {
        self.dir.join("optim.bpk")
    }

    /// The model record, read and decoded.
    pub fn model_record(&self) -> Result<ModuleRecord, TrainerError> {
        let path = self.model_path();
        let bytes = fs::read(&path).map_err(|e| TrainerError::io("reading", &path, e))?;
        decode_record(bytes, path)
    }
}

/// A model record (burnpack) from the bytes of `path` (named in the error).
pub fn decode_record(bytes: Vec<u8>, path: PathBuf) -> Result<ModuleRecord, TrainerError> {
    ModuleRecord::from_bytes(Bytes::from_bytes_vec(bytes))
        .map_err(|error| TrainerError::Record { path, error })
}

fn write_synced(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let mut f = File::create(path)?;
    f.write_all(bytes)?;
    f.sync_all()
}

fn sync_dir(dir: &Path) -> std::io::Result<()> {
    File::open(dir)?.sync_all()
}

/// Writes a checkpoint into `root` atomically and removes all but the `keep` newest.
/// A checkpoint that fails (a full disk) leaves nothing behind: its temporary files are
/// removed, so the failure does not keep the disk full.
pub fn save(
    root: &Path,
    state: &CheckpointState,
    model: &[u8],
    optim: &[u8],
    keep: usize,
) -> Result<PathBuf, TrainerError> {
    save_with(root, state, [model, optim], keep, write_synced)
}

/// [`save`] with the function that writes (and syncs) one file.
fn save_with(
    root: &Path,
    state: &CheckpointState,
    [model, optim]: [&[u8]; 2],
    keep: usize,
    write: impl Fn(&Path, &[u8]) -> std::io::Result<()>,
) -> Result<PathBuf, TrainerError> {
    let ctx = |action: &'static str, p: &Path, e| TrainerError::io(action, p, e);
    fs::create_dir_all(root).map_err(|e| ctx("checkpoint: creating", root, e))?;
    let name = format!("step-{:08}", state.step);
    let tmp = root.join(format!(".{name}.tmp-{}", std::process::id()));
    let latest_tmp = root.join(format!(".latest.tmp-{}", std::process::id()));
    let written = (|| {
        if tmp.exists() {
            fs::remove_dir_all(&tmp).map_err(|e| ctx("checkpoint: removing", &tmp, e))?;
        }
        fs::create_dir(&tmp).map_err(|e| ctx("checkpoint: creating", &tmp, e))?;
        let json = serde_json::to_vec_pretty(state).map_err(|error| TrainerError::Json {
            path: tmp.join("state.json"),
            error,
        })?;
        for (file, bytes) in [
            ("model.bpk", model),
            ("optim.bpk", optim),
            ("state.json", &json[..]),
        ] {
            let p = tmp.join(file);
            write(&p, bytes).map_err(|e| ctx("checkpoint: writing", &p, e))?;
        }
        sync_dir(&tmp).map_err(|e| ctx("checkpoint: syncing", &tmp, e))?;
        let dir = root.join(&name);
        if dir.exists() {
            fs::remove_dir_all(&dir).map_err(|e| ctx("checkpoint: replacing", &dir, e))?;
        }
        fs::rename(&tmp, &dir).map_err(|e| ctx("checkpoint: renaming into", &dir, e))?;
        write(&latest_tmp, name.as_bytes())
            .map_err(|e| ctx("checkpoint: writing", &latest_tmp, e))?;
        let latest = root.join("latest");
        fs::rename(&latest_tmp, &latest)
            .map_err(|e| ctx("checkpoint: renaming into", &latest, e))?;
        sync_dir(root).map_err(|e| ctx("checkpoint: syncing", root, e))?;
        Ok(dir)
    })();
    let dir = match written {
        Ok(dir) => dir,
        Err(e) => {
            // Best effort: the error being reported is the one that matters.
            let _ = fs::remove_dir_all(&tmp);
            let _ = fs::remove_file(&latest_tmp);
            return Err(e);
        }
    };
    prune(root, keep)?;
    Ok(dir)
}

/// Removes all but the `keep` newest complete checkpoints (never the one `latest` names).
fn prune(root: &Path, keep: usize) -> Result<(), TrainerError> {
    let latest = fs::read_to_string(root.join("latest")).unwrap_or_default();
    let mut names: Vec<String> = fs::read_dir(root)
        .map_err(|e| TrainerError::io("checkpoint: listing", root, e))?
        .filter_map(|e| e.ok())
        .filter_map(|e| e.file_name().into_string().ok())
        .filter(|n| n.starts_with("step-"))
        .collect();
    names.sort();
    let excess = names.len().saturating_sub(keep);
    for name in names.into_iter().take(excess) {
        if name != latest.trim() {
            let dir = root.join(&name);
            fs::remove_dir_all(&dir)
                .map_err(|e| TrainerError::io("checkpoint: removing", dir, e))?;
        }
    }
    Ok(())
}

/// The checkpoint `latest` names in `root`, if any. A damaged one is an error naming it.
pub fn latest(root: &Path) -> Result<Option<Checkpoint>, TrainerError> {
    let pointer = root.join("latest");
    let name = match fs::read_to_string(&pointer) {
        Ok(n) => n.trim().to_string(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(TrainerError::io("reading", pointer, e)),
    };
    read(&root.join(&name)).map(Some)
}

/// The checkpoint in `dir` (a `step-N` directory). A damaged one is an error naming it.
pub fn read(dir: &Path) -> Result<Checkpoint, TrainerError> {
    let dir = dir.to_path_buf();
    let state_path = dir.join("state.json");
    let text = fs::read(&state_path).map_err(|e| TrainerError::io("reading", &state_path, e))?;
    let state: CheckpointState = match serde_json::from_slice(&text) {
        Ok(state) => state,
        Err(error) => {
            return Err(TrainerError::Json {
                path: state_path,
                error,
            });
        }
    };
    if state.format != FORMAT {
        return Err(TrainerError::CheckpointFormat {
            path: state_path,
            found: state.format,
            expected: FORMAT,
        });
    }
    Ok(Checkpoint { dir, state })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(step: u64) -> CheckpointState {
        CheckpointState {
            format: FORMAT.into(),
            step,
            next_epoch: 0,
            next_batch: step,
            ranks: Vec::new(),
            job: None,
            run: "t".into(),
            config: String::new(),
            lr: 0.01,
            loss: 1.0,
        }
    }

    #[test]
    fn saves_atomically_keeps_the_newest_and_ignores_partial_writes() {
        let root = std::env::temp_dir().join(format!("superflow-ckpt-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        assert!(latest(&root).expect("no checkpoint is fine").is_none());
        for step in [10, 20, 30, 40] {
            save(&root, &state(step), b"model", b"optim", 2).expect("saved");
        }
        let last = latest(&root).expect("readable").expect("present");
        assert_eq!(last.state.step, 40);
        assert_eq!(fs::read(last.model_path()).expect("model"), b"model");
        let mut kept: Vec<String> = fs::read_dir(&root)
            .expect("dir")
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.starts_with("step-"))
            .collect();
        kept.sort();
        assert_eq!(kept, ["step-00000030", "step-00000040"]);
        // A crash mid-write leaves a temporary directory: `latest` still names step 40.
        let partial = root.join(".step-00000050.tmp-999");
        fs::create_dir(&partial).expect("partial");
        fs::write(partial.join("model.bpk"), b"half").expect("half");
        assert_eq!(
            latest(&root)
                .expect("readable")
                .expect("present")
                .state
                .step,
            40
        );
        fs::remove_dir_all(&root).expect("cleanup");
    }

    #[test]
    fn a_checkpoint_that_fails_on_a_full_disk_leaves_no_temporary_files() {
        let root = std::env::temp_dir().join(format!("superflow-ckpt-full-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        save(&root, &state(10), b"model", b"optim", 2).expect("saved");
        let before = fs::read_dir(&root).expect("dir").count();
        for failing in ["optim.bpk", "state.json", ".latest.tmp"] {
            let full = |p: &Path, bytes: &[u8]| {
                if p.to_string_lossy().contains(failing) {
                    // What a full disk answers; the part written so far stays.
                    fs::write(p, &bytes[..bytes.len() / 2])?;
                    return Err(std::io::Error::from(std::io::ErrorKind::StorageFull));
                }
                write_synced(p, bytes)
            };
            let err = save_with(&root, &state(20), [b"model", b"optim"], 2, full)
                .expect_err("the disk is full");
            assert!(err.to_string().contains("checkpoint: writing"), "{err}");
            let left: Vec<String> = fs::read_dir(&root)
                .expect("dir")
                .filter_map(|e| e.ok()?.file_name().into_string().ok())
                .filter(|n| n.starts_with('.'))
                .collect();
            assert!(left.is_empty(), "{failing}: left behind {left:?}");
            let latest = latest(&root).expect("readable").expect("present");
            if failing == ".latest.tmp" {
                // The directory was complete and renamed; `latest` still names step 10.
                assert!(root.join("step-00000020").exists());
                fs::remove_dir_all(root.join("step-00000020")).expect("reset");
            }
            assert_eq!(latest.state.step, 10, "{failing}");
            assert_eq!(fs::read_dir(&root).expect("dir").count(), before);
        }
        fs::remove_dir_all(&root).expect("cleanup");
    }
}
