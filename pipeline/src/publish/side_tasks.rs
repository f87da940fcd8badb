//! The service's side tasks, beside the publisher: SIGINT and SIGTERM stop it (after the
//! batch in flight, releasing its shared memory), and an optional Prometheus endpoint
//! serves [`Metrics`]. They run on a one-thread tokio runtime; building and publishing
//! keep their own threads (rayon, and the caller's).

use super::metrics::Metrics;
use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;
use tokio::signal::unix::{Signal, SignalKind, signal};

/// Why the side tasks could not start.
#[derive(Debug, thiserror::Error)]
pub enum SideTaskError {
    /// The tokio runtime could not be built.
    #[error("starting the runtime of the signal handlers and the metrics endpoint")]
    Runtime(#[source] std::io::Error),
    /// A signal handler could not be installed.
    #[error("installing the {signal} handler")]
    Signal {
        /// `SIGINT` or `SIGTERM`.
        signal: &'static str,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
    /// The metrics address could not be bound (in use, not local, no permission).
    #[error("binding the metrics address {addr}")]
    Bind {
        /// The `--metrics-addr`.
        addr: SocketAddr,
        /// What the system said.
        #[source]
        source: std::io::Error,
    },
}

/// The running side tasks; [`SideTasks::shutdown`] ends them.
#[derive(Debug)]
pub struct SideTasks {
    runtime: tokio::runtime::Runtime,
}

impl SideTasks {
    /// Installs the SIGINT and SIGTERM handlers, which set `stop`, and serves `metrics`
    /// at `http://{metrics_addr}/metrics` when given. Call it before anything is
    /// published: a signal then never takes its default action, which would leave
    /// shared memory behind.
    pub fn start(
        stop: Arc<AtomicBool>,
        metrics: Arc<Metrics>,
        metrics_addr: Option<SocketAddr>,
    ) -> Result<Self, SideTaskError> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .enable_all()
            .build()
            .map_err(SideTaskError::Runtime)?;
        let (int, term) = runtime.block_on(async {
            (
                signal(SignalKind::interrupt()),
                signal(SignalKind::terminate()),
            )
        });
        let installed = |signal, handler: std::io::Result<Signal>| {
            handler.map_err(|source| SideTaskError::Signal { signal, source })
        };
        let (int, term) = (installed("SIGINT", int)?, installed("SIGTERM", term)?);
        runtime.spawn(wait_for_signals(int, term, stop));
        if let Some(addr) = metrics_addr {
            let listener = runtime
                .block_on(tokio::net::TcpListener::bind(addr))
                .map_err(|source| SideTaskError::Bind { addr, source })?;
            tracing::info!(%addr, "metrics at http://{addr}/metrics");
            runtime.spawn(serve_metrics(listener, metrics));
        }
        Ok(Self { runtime })
    }

    /// Ends the handlers and the endpoint (a request being answered gets 100 ms).
    pub fn shutdown(self) {
        self.runtime.shutdown_timeout(Duration::from_millis(100));
    }
}

async fn wait_for_signals(mut int: Signal, mut term: Signal, stop: Arc<AtomicBool>) {
    let name = tokio::select! {
        _ = int.recv() => "SIGINT",
        _ = term.recv() => "SIGTERM",
    };
    // Stop first: logging can fail (a closed stderr) and must not keep us running.
    stop.store(true, Ordering::SeqCst);
    tracing::info!("{name}: finishing the batch in flight, releasing shared memory");
}

/// Answers every connection with the Prometheus text of `metrics`, whatever it asked.
async fn serve_metrics(listener: tokio::net::TcpListener, metrics: Arc<Metrics>) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    loop {
        let Ok((mut socket, _)) = listener.accept().await else {
            continue;
        };
        let metrics = metrics.clone();
        tokio::spawn(async move {
            let mut request = [0u8; 1024];
            let _ = socket.read(&mut request).await;
            let body = metrics.prometheus();
            let response = format!(
                "HTTP/1.1 200 OK\r\nContent-Type: text/plain; version=0.0.4\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = socket.write_all(response.as_bytes()).await;
        });
    }
}
