//! SIGTERM and SIGINT: stop after the step in progress, with a checkpoint.

use std::sync::Arc;
use std::sync::atomic::{AtomicI32, Ordering};

/// Watches SIGTERM and SIGINT (on a thread of its own): the first sets the returned
/// number (15 or 2) — the trainer checkpoints after the step in progress and exits
/// with the scheme's code of a signal ([`superflow_common::exit::signalled`]) — and a
/// second one exits at once, with the same code.
pub fn watch_signals() -> std::io::Result<Arc<AtomicI32>> {
    use tokio::signal::unix::{SignalKind, signal};
    let caught = Arc::new(AtomicI32::new(0));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_io()
        .build()?;
    let (mut term, mut int) = runtime.block_on(async {
        Ok::<_, std::io::Error>((
            signal(SignalKind::terminate())?,
            signal(SignalKind::interrupt())?,
        ))
    })?;
    let flag = caught.clone();
    std::thread::Builder::new()
        .name("signals".into())
        .spawn(move || {
            runtime.block_on(async move {
                loop {
                    let n = tokio::select! {
                        _ = term.recv() => 15,
                        _ = int.recv() => 2,
                    };
                    if flag.swap(n, Ordering::SeqCst) != 0 {
                        eprintln!("superflow-trainer: second signal, exiting without a checkpoint");
                        std::process::exit(i32::from(superflow_common::exit::signalled(n)));
                    }
                    tracing::warn!(
                        signal = n,
                        "stopping: a checkpoint is written after the step in progress (signal again to exit at once)"
                    );
                }
            });
        })?;
    Ok(caught)
}
