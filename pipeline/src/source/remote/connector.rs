//! The HTTP client every object store of this process uses: object_store's own reqwest
//! client, wrapped so that each attempt — first tries and the client's retries alike —
//! is counted by outcome and timed ([`super::stats`]). The retry policy stays
//! object_store's ([`RetryConfig`](object_store::RetryConfig)): this layer only watches.

use super::stats::{self, Failure, RequestKind};
use bytes::Bytes;
use http_body::{Body, Frame, SizeHint};
use object_store::client::{
    ClientOptions, HttpClient, HttpConnector, HttpError, HttpErrorKind, HttpRequest, HttpResponse,
    HttpResponseBody, HttpService, ReqwestConnector,
};
use std::pin::Pin;
use std::task::{Context, Poll};
use std::time::Instant;

/// Builds object_store's reqwest client and wraps it in [`Counted`].
#[derive(Debug, Default)]
pub(super) struct CountingConnector;

impl HttpConnector for CountingConnector {
    fn connect(&self, options: &ClientOptions) -> object_store::Result<HttpClient> {
        let inner = ReqwestConnector::default().connect(options)?;
        Ok(HttpClient::new(Counted(inner)))
    }
}

#[derive(Debug)]
struct Counted(HttpClient);

#[async_trait::async_trait]
impl HttpService for Counted {
    async fn call(&self, req: HttpRequest) -> Result<HttpResponse, HttpError> {
        let kind = match *req.method() {
            http::Method::GET
                if req
                    .uri()
                    .query()
                    .is_some_and(|q| q.contains("list-type") || q.contains("comp=list")) =>
            {
                RequestKind::List
            }
            http::Method::GET => RequestKind::Get,
            http::Method::HEAD => RequestKind::Head,
            _ => RequestKind::Other,
        };
        stats::count_request(kind);
        let started = Instant::now();
        let result = self.0.execute(req).await;
        stats::count_latency(started.elapsed());
        match result {
            Ok(response) => {
                let status = response.status().as_u16();
                match status {
                    429 | 503 => stats::count_failure(Failure::Throttled),
                    408 => stats::count_failure(Failure::Timeout),
                    500..=599 => stats::count_failure(Failure::ServerError),
                    _ => {}
                }
                Ok(response.map(|body| HttpResponseBody::new(WatchedBody(body))))
            }
            Err(e) => {
                stats::count_failure(match e.kind() {
                    HttpErrorKind::Timeout => Failure::Timeout,
                    _ => Failure::Connection,
                });
                Err(e)
            }
        }
    }
}

/// A response body that counts its failure mid-stream (a body cut short).
struct WatchedBody(HttpResponseBody);

impl Body for WatchedBody {
    type Data = Bytes;
    type Error = HttpError;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Bytes>, HttpError>>> {
        let polled = Pin::new(&mut self.0).poll_frame(cx);
        if let Poll::Ready(Some(Err(_))) = &polled {
            stats::count_failure(Failure::BodyCut);
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.0.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.0.size_hint()
    }
}
