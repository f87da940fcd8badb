//! An HTTP/1.1 proxy on 127.0.0.1 in front of the local S3 server that injects latency, a
//! bandwidth cap and faults (S3 `SlowDown`/`InternalError` answers, resets, cut bodies,
//! slow first bytes) per a [`FaultPlan`], and counts requests by kind: the object-storage
//! reader's retries, resumes and request counts are tested and benchmarked against it.
//!
//! Clients keep their connection alive (request and response bodies are framed by
//! `Content-Length` or chunked encoding and forwarded as they are); each request goes
//! upstream on a fresh connection with `Connection: close`. Headers are forwarded
//! unchanged (`Host` included, so SigV4 signatures still match), except `Connection`,
//! `Keep-Alive` and `Expect`. The proxy runs on its own tokio runtime, shut down on drop.

use super::Counters;
use super::plan::{Fault, FaultPlan, RequestKind, State};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::io::{
    AsyncBufRead, AsyncBufReadExt, AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, BufReader,
};
use tokio::net::{TcpListener, TcpStream};
use tokio::time::Instant;

/// Largest request or response head accepted.
const MAX_HEAD: usize = 64 * 1024;
/// Largest piece of body forwarded at once.
const PIECE: usize = 16 * 1024;
/// How far ahead of the bandwidth schedule a piece may go (a few timer ticks: the cap
/// holds on average, bursts stay below this much of it).
const PACE_SLACK: Duration = Duration::from_millis(3);
/// Bound on waiting for upstream's response head (moto answers in milliseconds).
const UPSTREAM_TIMEOUT: Duration = Duration::from_secs(60);

/// The fault-injecting proxy; see the module docs. Stops (every connection task with it)
/// when dropped.
#[derive(Debug)]
pub struct FaultProxy {
    addr: SocketAddr,
    shared: Arc<Shared>,
    runtime: Option<tokio::runtime::Runtime>,
}

#[derive(Debug)]
struct Shared {
    upstream: SocketAddr,
    state: Mutex<State>,
    /// When the shared bandwidth budget is next free.
    link_free_at: Mutex<Instant>,
}

impl Shared {
    fn state(&self) -> MutexGuard<'_, State> {
        self.state
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Waits until `n` bytes fit in the bandwidth budget of `rate` bytes per second.
    ///
    /// The link is booked piece by piece on one schedule; a piece goes once its booking
    /// ends less than [`PACE_SLACK`] ahead. Sleeping until each piece's own end instead
    /// would round every piece up to tokio's 1 ms timer tick: one connection could then
    /// never pass more than a piece per millisecond (16 MB/s), whatever the cap.
    async fn pace(&self, rate: u64, n: usize) {
        let until = {
            let mut free_at = self
                .link_free_at
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            let start = (*free_at).max(Instant::now());
            *free_at = start + Duration::from_secs_f64(n as f64 / rate as f64);
            *free_at
        };
        if let Some(wake) = until.checked_sub(PACE_SLACK)
            && wake > Instant::now()
        {
            tokio::time::sleep_until(wake).await;
        }
    }
}

/// Paces (to the plan's bandwidth) and counts the response body bytes forwarded.
#[derive(Debug, Clone, Copy)]
struct Meter<'a> {
    shared: &'a Shared,
    rate: Option<u64>,
}

impl Meter<'_> {
    /// The size of the pieces forwarded: ~20 ms of the budget, for smooth pacing.
    fn piece(meter: Option<Self>) -> usize {
        match meter.and_then(|m| m.rate) {
            Some(rate) => usize::try_from(rate / 50)
                .unwrap_or(PIECE)
                .clamp(1024, PIECE),
            None => PIECE,
        }
    }

    /// Called before `n` bytes are written.
    async fn before(meter: Option<Self>, n: usize) {
        if let Some(Self { shared, rate }) = meter {
            if let Some(rate) = rate {
                shared.pace(rate, n).await;
            }
            shared.state().counters.body_bytes += n as u64;
        }
    }
}

impl FaultProxy {
    /// Starts a proxy to `upstream` (an `http://host:port` endpoint or `host:port`) on a
    /// free port of 127.0.0.1. Panics if the plan is invalid or nothing can be bound.
    pub fn start(upstream: &str, plan: FaultPlan) -> Self {
        if let Err(e) = plan.validate() {
            panic!("FaultProxy: {e}");
        }
        let authority = upstream.trim_start_matches("http://").trim_end_matches('/');
        let upstream: SocketAddr = authority
            .parse()
            .unwrap_or_else(|e| panic!("FaultProxy: upstream {authority:?} is not ip:port: {e}"));
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("fault-proxy")
            .enable_all()
            .build()
            .unwrap_or_else(|e| panic!("FaultProxy: tokio runtime: {e}"));
        let listener = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap_or_else(|e| panic!("FaultProxy: binding 127.0.0.1:0: {e}"));
        let addr = listener
            .local_addr()
            .unwrap_or_else(|e| panic!("FaultProxy: local address: {e}"));
        listener
            .set_nonblocking(true)
            .unwrap_or_else(|e| panic!("FaultProxy: non-blocking listener: {e}"));
        let shared = Arc::new(Shared {
            upstream,
            state: Mutex::new(State::new(plan)),
            link_free_at: Mutex::new(Instant::now()),
        });
        let listener = {
            let _entered = runtime.enter();
            TcpListener::from_std(listener)
                .unwrap_or_else(|e| panic!("FaultProxy: tokio listener: {e}"))
        };
        runtime.spawn(accept_loop(listener, Arc::clone(&shared)));
        Self {
            addr,
            shared,
            runtime: Some(runtime),
        }
    }

    /// `http://127.0.0.1:PORT`, the endpoint clients use instead of upstream's.
    pub fn endpoint(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// The port the proxy listens on.
    pub fn port(&self) -> u16 {
        self.addr.port()
    }

    /// The plan in force.
    pub fn plan(&self) -> FaultPlan {
        self.shared.state().plan.clone()
    }

    /// Replaces the plan for the requests that arrive from now on (requests in flight
    /// keep theirs); the "once" memory and the Nth-request count start over. Panics if
    /// the plan is invalid.
    pub fn set_plan(&self, plan: FaultPlan) {
        if let Err(e) = plan.validate() {
            panic!("FaultProxy: {e}");
        }
        self.shared.state().set_plan(plan);
    }

    /// What the proxy saw so far.
    pub fn counters(&self) -> Counters {
        self.shared.state().counters
    }

    /// Zeroes the counters.
    pub fn reset_counters(&self) {
        self.shared.state().reset_counters();
    }
}

impl Drop for FaultProxy {
    fn drop(&mut self) {
        if let Some(runtime) = self.runtime.take() {
            // Drops every task (listener and connections) without waiting; allowed
            // inside another runtime too.
            runtime.shutdown_background();
        }
    }
}

async fn accept_loop(listener: TcpListener, shared: Arc<Shared>) {
    loop {
        match listener.accept().await {
            Ok((stream, _)) => {
                let _ = stream.set_nodelay(true);
                tokio::spawn(serve_connection(stream, Arc::clone(&shared)));
            }
            // Out of descriptors or the like: try again shortly.
            Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
        }
    }
}

/// A request or response head: its first line and its headers.
#[derive(Debug)]
struct Head {
    first: String,
    headers: Vec<(String, String)>,
}

impl Head {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.trim())
    }

    fn has_token(&self, name: &str, token: &str) -> bool {
        self.headers.iter().any(|(n, v)| {
            n.eq_ignore_ascii_case(name)
                && v.split(',').any(|t| t.trim().eq_ignore_ascii_case(token))
        })
    }

    /// How the body that follows this head is framed.
    fn framing(&self) -> std::io::Result<Framing> {
        if self.has_token("transfer-encoding", "chunked") {
            return Ok(Framing::Chunked);
        }
        match self.header("content-length") {
            Some(n) => n.parse().map(Framing::Length).map_err(|_| {
                std::io::Error::new(std::io::ErrorKind::InvalidData, "bad Content-Length")
            }),
            None => Ok(Framing::Eof),
        }
    }

    /// The head with `Connection`, `Keep-Alive` and `Expect` left out and
    /// `Connection: close` added if `close`.
    fn encode(&self, first: &str, close: bool) -> Vec<u8> {
        let mut out = format!("{first}\r\n");
        for (name, value) in &self.headers {
            if ["connection", "keep-alive", "proxy-connection", "expect"]
                .iter()
                .any(|h| name.eq_ignore_ascii_case(h))
            {
                continue;
            }
            out.push_str(&format!("{name}: {value}\r\n"));
        }
        if close {
            out.push_str("Connection: close\r\n");
        }
        out.push_str("\r\n");
        out.into_bytes()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Framing {
    Length(u64),
    Chunked,
    /// Until the sender closes (a response without length) or none (a request).
    Eof,
}

/// Reads a head; `None` at a clean end of stream before its first byte.
async fn read_head<R: AsyncBufRead + Unpin>(reader: &mut R) -> std::io::Result<Option<Head>> {
    let mut lines = Vec::new();
    let mut size = 0;
    loop {
        let mut line = Vec::new();
        let n = reader.read_until(b'\n', &mut line).await?;
        if n == 0 {
            if lines.is_empty() && size == 0 {
                return Ok(None);
            }
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        size += n;
        if size > MAX_HEAD {
            return Err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "head too large",
            ));
        }
        let line = String::from_utf8_lossy(&line)
            .trim_end_matches(['\r', '\n'])
            .to_owned();
        if line.is_empty() {
            if lines.is_empty() {
                continue; // stray CRLF between messages
            }
            break;
        }
        lines.push(line);
    }
    let mut lines = lines.into_iter();
    let first = lines.next().unwrap_or_default();
    let headers = lines
        .filter_map(|l| {
            l.split_once(':')
                .map(|(n, v)| (n.trim().to_owned(), v.trim().to_owned()))
        })
        .collect();
    Ok(Some(Head { first, headers }))
}

/// Copies `n` bytes (an error if the source ends before).
async fn copy_exact<R, W>(
    from: &mut R,
    to: &mut W,
    n: u64,
    meter: Option<Meter<'_>>,
) -> std::io::Result<()>
where
    R: AsyncRead + Unpin,
    W: AsyncWrite + Unpin,
{
    let piece = Meter::piece(meter);
    let mut buf = vec![0u8; piece];
    let mut done = 0u64;
    while done < n {
        let want = usize::try_from(n - done).map_or(piece, |left| left.min(piece));
        let got = from.read(&mut buf[..want]).await?;
        if got == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        Meter::before(meter, got).await;
        to.write_all(&buf[..got]).await?;
        done += got as u64;
    }
    Ok(())
}

/// Copies a chunked body as it is (sizes, extensions, trailers; all counted as body).
async fn copy_chunked<R, W>(
    from: &mut R,
    to: &mut W,
    meter: Option<Meter<'_>>,
) -> std::io::Result<()>
where
    R: AsyncBufRead + Unpin,
    W: AsyncWrite + Unpin,
{
    loop {
        let mut line = Vec::new();
        if from.read_until(b'\n', &mut line).await? == 0 {
            return Err(std::io::ErrorKind::UnexpectedEof.into());
        }
        Meter::before(meter, line.len()).await;
        to.write_all(&line).await?;
        let text = String::from_utf8_lossy(&line);
        let size = text.split(';').next().unwrap_or_default().trim();
        let size = u64::from_str_radix(size, 16)
            .map_err(|_| std::io::Error::new(std::io::ErrorKind::InvalidData, "bad chunk size"))?;
        if size == 0 {
            // Trailers, up to the empty line.
            loop {
                let mut line = Vec::new();
                if from.read_until(b'\n', &mut line).await? == 0 {
                    return Err(std::io::ErrorKind::UnexpectedEof.into());
                }
                Meter::before(meter, line.len()).await;
                to.write_all(&line).await?;
                if line == b"\r\n" || line == b"\n" {
                    return Ok(());
                }
            }
        }
        copy_exact(from, to, size + 2, meter).await?;
    }
}

/// Serves one client connection, request after request, until either side closes.
async fn serve_connection(stream: TcpStream, shared: Arc<Shared>) {
    let (read, mut write) = stream.into_split();
    let mut client = BufReader::new(read);
    // Every error ends the connection, which is what the client sees of it.
    while let Ok(true) = serve_request(&mut client, &mut write, &shared).await {}
    let _ = write.shutdown().await;
}

/// Serves one request; `Ok(true)` if the connection stays open for the next.
async fn serve_request<R, W>(
    client: &mut BufReader<R>,
    out: &mut W,
    shared: &Shared,
) -> std::io::Result<bool>
where
    R: AsyncRead + Unpin,
    W: AsyncWrite + Unpin,
{
    let Some(request) = read_head(client).await? else {
        return Ok(false);
    };
    let mut parts = request.first.split_whitespace();
    let method = parts.next().unwrap_or_default().to_owned();
    let target = parts.next().unwrap_or_default().to_owned();
    let version = parts.next().unwrap_or_default().to_owned();
    let range = request.header("range").unwrap_or_default().to_owned();
    let kind = RequestKind::classify(&method, &target, !range.is_empty());
    let key = format!("{method} {target} {range}");
    let (plan, fault) = {
        let mut state = shared.state();
        let fault = state.decide(kind, &key);
        (state.plan.clone(), fault)
    };
    let client_close = request.has_token("connection", "close") || version == "HTTP/1.0";
    let request_framing = match request.framing()? {
        Framing::Eof => Framing::Length(0), // a request without length has no body
        framing => framing,
    };
    if request.has_token("expect", "100-continue") {
        out.write_all(b"HTTP/1.1 100 Continue\r\n\r\n").await?;
    }

    let status = match fault {
        Some(Fault::Reset) => {
            tokio::time::sleep(plan.latency).await;
            return Ok(false);
        }
        Some(Fault::Status503) => Some((
            503,
            "Service Unavailable",
            "SlowDown",
            "Please reduce your request rate.",
        )),
        Some(Fault::Status500) => Some((
            500,
            "Internal Server Error",
            "InternalError",
            "We encountered an internal error. Please try again.",
        )),
        _ => None,
    };
    if let Some((code, reason, s3_code, message)) = status {
        // The request's body is read and dropped so that the connection can go on.
        let mut sink = tokio::io::sink();
        match request_framing {
            Framing::Chunked => {
                copy_chunked(client, &mut sink, None).await?;
            }
            Framing::Length(n) => {
                copy_exact(client, &mut sink, n, None).await?;
            }
            Framing::Eof => {}
        }
        tokio::time::sleep(plan.latency).await;
        let body = format!(
            "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<Error><Code>{s3_code}</Code>\
             <Message>{message}</Message><RequestId>fault-proxy</RequestId></Error>"
        );
        let head = format!(
            "HTTP/1.1 {code} {reason}\r\nContent-Type: application/xml\r\n\
             Content-Length: {}\r\n{}\r\n",
            body.len(),
            if client_close {
                "Connection: close\r\n"
            } else {
                ""
            }
        );
        out.write_all(head.as_bytes()).await?;
        if method != "HEAD" {
            out.write_all(body.as_bytes()).await?;
        }
        out.flush().await?;
        return Ok(!client_close);
    }

    // Forward upstream on a fresh connection.
    let upstream = match TcpStream::connect(shared.upstream).await {
        Ok(upstream) => upstream,
        Err(e) => {
            let body = format!("fault proxy: upstream {}: {e}", shared.upstream);
            let head = format!(
                "HTTP/1.1 502 Bad Gateway\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            );
            out.write_all(head.as_bytes()).await?;
            out.write_all(body.as_bytes()).await?;
            return Ok(false);
        }
    };
    let _ = upstream.set_nodelay(true);
    let (up_read, mut up_write) = upstream.into_split();
    let mut up_read = BufReader::new(up_read);
    up_write
        .write_all(&request.encode(&request.first, true))
        .await?;
    match request_framing {
        Framing::Chunked => {
            copy_chunked(client, &mut up_write, None).await?;
        }
        Framing::Length(n) => {
            copy_exact(client, &mut up_write, n, None).await?;
        }
        Framing::Eof => {}
    }
    up_write.flush().await?;

    let response = tokio::time::timeout(UPSTREAM_TIMEOUT, read_head(&mut up_read))
        .await
        .map_err(|_| std::io::Error::from(std::io::ErrorKind::TimedOut))??
        .ok_or(std::io::ErrorKind::UnexpectedEof)?;
    let mut status_parts = response.first.splitn(2, ' ');
    let _ = status_parts.next();
    let rest = status_parts.next().unwrap_or_default().to_owned();
    let code: u16 = rest
        .split_whitespace()
        .next()
        .and_then(|c| c.parse().ok())
        .unwrap_or(0);
    if matches!(kind, RequestKind::GetObject | RequestKind::RangedGet)
        && let Some(bytes) = served_range(code, &response)
    {
        let object = target.split('?').next().unwrap_or_default();
        shared.state().cover(object, bytes);
    }
    let no_body = method == "HEAD" || (100..200).contains(&code) || code == 204 || code == 304;
    let framing = if no_body {
        Framing::Length(0)
    } else {
        response.framing()?
    };
    let cut = fault == Some(Fault::Cut);
    let close = client_close || cut || framing == Framing::Eof;

    let mut wait = plan.latency;
    if fault == Some(Fault::SlowFirstByte) {
        wait += plan.slow_first_byte;
    }
    tokio::time::sleep(wait).await;
    out.write_all(&response.encode(&format!("HTTP/1.1 {rest}"), close))
        .await?;
    let meter = Some(Meter {
        shared,
        rate: plan.bandwidth_bytes_per_sec,
    });
    match framing {
        // Half of the body, then the connection closes.
        Framing::Length(n) if cut => copy_exact(&mut up_read, out, n / 2, meter).await?,
        // A body without length is cut before its first byte.
        _ if cut => {}
        Framing::Length(n) => copy_exact(&mut up_read, out, n, meter).await?,
        Framing::Chunked => copy_chunked(&mut up_read, out, meter).await?,
        Framing::Eof => copy_to_eof(&mut up_read, out, meter).await?,
    }
    out.flush().await?;
    Ok(!close)
}

/// The bytes of the object a GET's response carries: `Content-Range` of a 206, the whole
/// `Content-Length` of a 200.
fn served_range(code: u16, response: &Head) -> Option<std::ops::Range<u64>> {
    match code {
        206 => {
            let range = response.header("content-range")?.strip_prefix("bytes ")?;
            let (span, _) = range.split_once('/')?;
            let (first, last) = span.split_once('-')?;
            let (first, last): (u64, u64) = (first.trim().parse().ok()?, last.trim().parse().ok()?);
            (first <= last).then(|| first..last + 1)
        }
        200 => Some(0..response.header("content-length")?.parse().ok()?),
        _ => None,
    }
}

/// Copies until the source ends.
async fn copy_to_eof<R, W>(
    from: &mut R,
    to: &mut W,
    meter: Option<Meter<'_>>,
) -> std::io::Result<()>
where
    R: AsyncRead + Unpin,
    W: AsyncWrite + Unpin,
{
    let mut buf = vec![0u8; Meter::piece(meter)];
    loop {
        let got = from.read(&mut buf).await?;
        if got == 0 {
            return Ok(());
        }
        Meter::before(meter, got).await;
        to.write_all(&buf[..got]).await?;
    }
}
