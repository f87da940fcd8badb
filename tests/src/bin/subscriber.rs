//! `superflow-subscriber`: a test subscriber. Reads batches of a run and prints one JSON line
//! per batch (sequence, epoch, step, sample ids, each sample's camera count, a hash of the
//! payload; `"lost":true` and no sample for a lost batch) so end-to-end tests can account
//! for every sample; can stall (stop reading) or resume at a position (a step of its
//! stream, or a sample count of the whole job). At the end it says on stderr how many
//! batches it read and how many of them were lost.

use clap::Parser;
use std::io::Write as _;
use std::time::Duration;
use superflow_schemas::batch::Section;
use superflow_schemas::service::UNKNOWN;
use superflow_trainer::subscribe::{ResumeAt, Subscription, Target};

#[derive(Debug, Parser)]
struct Args {
    /// Run name.
    #[arg(long)]
    run: String,
    /// Shard rank; broadcast when absent.
    #[arg(long)]
    rank: Option<u32>,
    /// Batches to read before exiting.
    #[arg(long)]
    count: usize,
    /// Receive queue length.
    #[arg(long, default_value_t = 2)]
    buffer: usize,
    /// Give up (exit 3) when no batch arrives for this long.
    #[arg(long, default_value_t = 60)]
    timeout_secs: u64,
    /// After this many batches stop reading for `stall_secs` (forever when 0).
    #[arg(long)]
    stall_after: Option<usize>,
    /// See `stall_after`.
    #[arg(long, default_value_t = 0)]
    stall_secs: u64,
    /// Before reading, ask the pipeline to resume this stream at EPOCH STEP.
    #[arg(long, num_args = 2, conflicts_with = "resume_sample")]
    resume: Option<Vec<u64>>,
    /// Before reading, ask the pipeline to resume this stream after SAMPLE samples of
    /// EPOCH consumed by the whole job (EPOCH SAMPLE).
    #[arg(long, num_args = 2)]
    resume_sample: Option<Vec<u64>>,
    /// After this many batches, ask to resume at `resume_to` (EPOCH STEP).
    #[arg(long)]
    resume_after: Option<usize>,
    /// See `resume_after`.
    #[arg(long, num_args = 2)]
    resume_to: Option<Vec<u64>>,
    /// Print each section's dtype, shape and checksum (as `trainer/python/tests/check_stream.py`).
    #[arg(long)]
    sections: bool,
    /// iceoryx2 isolation prefix.
    #[arg(long, env = "SUPERFLOW_IOX_PREFIX")]
    iox_prefix: Option<String>,
}

/// `sum_i (b_i + 1) * (i * K + 1) mod 2^64`, the checksum `check_stream.py` computes with
/// numpy.
fn checksum(bytes: &[u8]) -> u64 {
    bytes.iter().enumerate().fold(0u64, |acc, (i, b)| {
        let w = (i as u64)
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(1);
        acc.wrapping_add((u64::from(*b) + 1).wrapping_mul(w))
    })
}

/// FNV-1a over the bytes the header's sections cover.
fn fnv(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01B3)
    })
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let iox = superflow_schemas::service::iceoryx2_config(args.iox_prefix.as_deref())
        .map_err(|e| anyhow::anyhow!(e))?;
    let target = args.rank.map_or(Target::Broadcast, Target::Rank);
    let subscription = Subscription::open(&args.run, target, &iox, args.buffer)?;
    let out = std::io::stdout();
    let resume = |at: ResumeAt| -> anyhow::Result<()> {
        let reply = subscription.resume(at, Duration::from_secs(30))?;
        let (kind, value) = match at {
            ResumeAt::Step { step, .. } => ("resume", step),
            ResumeAt::Sample { sample, .. } => ("resume_sample", sample),
        };
        writeln!(
            out.lock(),
            "{{\"{kind}\":[{},{value}],\"accepted\":{},\"reason\":{},\"at\":[{},{}],\"next_sequence\":{},\"publisher\":\"{:x}\"}}",
            at.epoch(),
            reply.accepted,
            reply.reason,
            reply.epoch,
            reply.step,
            reply.next_sequence,
            reply.publisher()
        )?;
        Ok(())
    };
    let step = |position: &[u64]| ResumeAt::Step {
        epoch: position[0],
        step: position[1],
    };
    if let Some(position) = &args.resume {
        resume(step(position))?;
    }
    if let Some(position) = &args.resume_sample {
        resume(ResumeAt::Sample {
            epoch: position[0],
            sample: position[1],
            global_batch: UNKNOWN,
        })?;
    }
    let mut lost = 0usize;
    for n in 0..args.count {
        if args.stall_after == Some(n) {
            if args.stall_secs == 0 {
                loop {
                    std::thread::sleep(Duration::from_secs(3600));
                }
            }
            std::thread::sleep(Duration::from_secs(args.stall_secs));
        }
        if args.resume_after == Some(n)
            && let Some(position) = &args.resume_to
        {
            resume(step(position))?;
        }
        let Some(batch) = subscription.receive(Duration::from_secs(args.timeout_secs))? else {
            eprintln!(
                "superflow-subscriber: no batch within {} s after {n}",
                args.timeout_secs
            );
            // A stream gone quiet: the peer is gone, not a failed data-parallel job.
            std::process::exit(i32::from(superflow_common::exit::FAILED));
        };
        let view = batch.view()?;
        let meta = view.meta();
        if view.is_lost() {
            lost += 1;
            writeln!(
                out.lock(),
                "{{\"sequence\":{},\"epoch\":{},\"step\":{},\"lost\":true,\"samples\":[],\"cameras\":[],\"hash\":{},\"origin\":\"{:x}\"}}",
                meta.sequence,
                meta.epoch,
                meta.step,
                fnv(&[]),
                batch.origin()
            )?;
            continue;
        }
        let ids = view.section::<u64>(Section::SampleIds)?;
        let samples: Vec<String> = ids
            .data
            .chunks_exact(5)
            .map(|s| format!("[{},{},{},{},{}]", s[0], s[1], s[2], s[3], s[4]))
            .collect();
        let slots = view.section::<u32>(Section::SampleCameras)?;
        let cameras: Vec<String> = slots
            .data
            .windows(2)
            .map(|w| (w[1] - w[0]).to_string())
            .collect();
        let covered = &batch.payload()[..batch.header().payload_len as usize];
        let sections = if args.sections {
            let entries: Vec<String> = view
                .section_names()
                .map(|name| {
                    let (dtype, shape) = view.describe(name).map_err(|e| anyhow::anyhow!(e))?;
                    let bytes = view.bytes(name).map_err(|e| anyhow::anyhow!(e))?;
                    Ok(format!(
                        "\"{name}\":{{\"dtype\":\"{}\",\"shape\":{shape:?},\"checksum\":{}}}",
                        dtype.numpy(),
                        checksum(bytes)
                    ))
                })
                .collect::<anyhow::Result<_>>()?;
            format!(",\"sections\":{{{}}}", entries.join(","))
        } else {
            String::new()
        };
        writeln!(
            out.lock(),
            "{{\"sequence\":{},\"epoch\":{},\"step\":{},\"samples\":[{}],\"cameras\":[{}],\"hash\":{},\"origin\":\"{:x}\"{sections}}}",
            meta.sequence,
            meta.epoch,
            meta.step,
            samples.join(","),
            cameras.join(","),
            fnv(covered),
            batch.origin()
        )?;
    }
    eprintln!(
        "superflow-subscriber: {} batches read, {lost} of them lost",
        args.count
    );
    Ok(())
}
