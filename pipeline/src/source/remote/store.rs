//! One `object_store` client per store (`s3://bucket`, `gs://bucket`, `az://container`,
//! `https://host`), built once from the environment the way the `object_store` crate
//! documents it (`AWS_*`, `GOOGLE_*`, `AZURE_*`), with the retry bound and timeouts of
//! [`RemoteSettings`], and the runtime its requests run on.

use super::connector::CountingConnector;
use super::url::ObjectUrl;
use object_store::client::ClientConfigKey;
use object_store::{ObjectStore, RetryConfig};
use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, LazyLock, Mutex, PoisonError, RwLock};
use std::time::Duration;

/// How the process talks to object stores: `[ingest] remote_*` in pipeline.toml.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RemoteSettings {
    /// Retries of one request (throttling, 5xx, timeouts, resets, cut bodies), with
    /// exponential backoff and jitter, before its read fails.
    pub retries: usize,
    /// The longest one request may take, its whole body included; also bounds the time
    /// spent retrying it (four times this).
    pub request_timeout: Duration,
    /// Requests in flight at once, demand reads and prefetches together.
    pub concurrency: usize,
    /// Bytes read ahead of the samples that need them, at most.
    pub prefetch_bytes: u64,
    /// A read longer than this is split into parts of this size fetched in parallel.
    pub part_bytes: u64,
}

impl Default for RemoteSettings {
    fn default() -> Self {
        RemoteSettings {
            retries: 10,
            request_timeout: Duration::from_secs(30),
            concurrency: 32,
            prefetch_bytes: 256 << 20,
            part_bytes: 8 << 20,
        }
    }
}

static SETTINGS: RwLock<Option<RemoteSettings>> = RwLock::new(None);

/// Sets how this process talks to object stores. Stores already built keep their retry
/// and timeout settings; call it before the first remote path is opened.
pub fn configure(settings: RemoteSettings) {
    *SETTINGS.write().unwrap_or_else(PoisonError::into_inner) = Some(settings);
}

/// The settings in force.
pub fn settings() -> RemoteSettings {
    SETTINGS
        .read()
        .unwrap_or_else(PoisonError::into_inner)
        .unwrap_or_default()
}

/// The runtime every request runs on: a few threads that only wait on sockets.
static RUNTIME: LazyLock<tokio::runtime::Runtime> = LazyLock::new(|| {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("object-store")
        .enable_all()
        .build()
        .expect("the object-store runtime starts") // only fails without threads or sockets
});

/// Requests in flight, bounded by [`RemoteSettings::concurrency`].
static IN_FLIGHT: LazyLock<Arc<tokio::sync::Semaphore>> =
    LazyLock::new(|| Arc::new(tokio::sync::Semaphore::new(settings().concurrency.max(1))));

/// Runs `future` on the object-store runtime and waits for it, from any thread (a rayon
/// worker, or a thread that runs a runtime of its own).
pub(super) fn block_on<T: Send + 'static>(future: impl Future<Output = T> + Send + 'static) -> T {
    let handle = RUNTIME.spawn(future);
    match futures::executor::block_on(handle) {
        Ok(value) => value,
        Err(e) => std::panic::resume_unwind(e.into_panic()),
    }
}

/// Spawns `future` on the object-store runtime without waiting.
pub(super) fn spawn<T: Send + 'static>(
    future: impl Future<Output = T> + Send + 'static,
) -> tokio::task::JoinHandle<T> {
    RUNTIME.spawn(future)
}

/// A permit to send one request (see [`IN_FLIGHT`]).
pub(super) async fn permit() -> tokio::sync::OwnedSemaphorePermit {
    Arc::clone(&IN_FLIGHT)
        .acquire_owned()
        .await
        .expect("the request semaphore is never closed")
}

/// `path` as an object URL and the client of its store: what every request starts from.
pub(super) fn open_url(
    path: &std::path::Path,
) -> Result<(ObjectUrl, Arc<dyn ObjectStore>), crate::source::SourceError> {
    let remote = |reason: String| crate::source::SourceError::Remote {
        path: path.to_path_buf(),
        reason,
    };
    let url = ObjectUrl::parse(path).ok_or_else(|| remote("not an object URL".into()))?;
    let store = store_of(&url).map_err(remote)?;
    Ok((url, store))
}

/// The client of the store `url` is in, built on first use.
fn store_of(url: &ObjectUrl) -> Result<Arc<dyn ObjectStore>, String> {
    static STORES: LazyLock<Mutex<HashMap<String, Arc<dyn ObjectStore>>>> =
        LazyLock::new(Default::default);
    let mut stores = STORES.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(store) = stores.get(&url.store) {
        return Ok(Arc::clone(store));
    }
    let store = build(url).map_err(|e| super::redact(&e.to_string()))?;
    stores.insert(url.store.clone(), Arc::clone(&store));
    Ok(store)
}

/// The retry policy: object_store's exponential backoff with jitter, bounded.
fn retry(settings: &RemoteSettings) -> RetryConfig {
    RetryConfig {
        max_retries: settings.retries,
        retry_timeout: settings.request_timeout * 4,
        ..RetryConfig::default()
    }
}

fn build(url: &ObjectUrl) -> object_store::Result<Arc<dyn ObjectStore>> {
    use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
    use object_store::azure::{AzureConfigKey, MicrosoftAzureBuilder};
    use object_store::gcp::{GoogleCloudStorageBuilder, GoogleConfigKey};
    use object_store::http::HttpBuilder;
    let settings = settings();
    let timeout = format!("{}s", settings.request_timeout.as_secs().max(1));
    // The request timeout covers a whole body; a part is at most `part_bytes`.
    let env_has = |key: &str| std::env::var_os(key).is_some();
    let root = format!("{}/", url.store);
    Ok(match url.scheme() {
        "s3" | "s3a" => {
            let mut builder = AmazonS3Builder::from_env().with_url(root);
            if !env_has("AWS_TIMEOUT") {
                builder = builder
                    .with_config(AmazonS3ConfigKey::Client(ClientConfigKey::Timeout), timeout);
            }
            // A MinIO or Ceph endpoint on plain HTTP is what its user asked for.
            let plain_http = ["AWS_ENDPOINT_URL", "AWS_ENDPOINT", "AWS_ENDPOINT_URL_S3"]
                .iter()
                .any(|k| std::env::var(k).is_ok_and(|v| v.starts_with("http://")));
            if plain_http && !env_has("AWS_ALLOW_HTTP") {
                builder = builder.with_allow_http(true);
            }
            Arc::new(
                builder
                    .with_retry(retry(&settings))
                    .with_http_connector(CountingConnector)
                    .build()?,
            )
        }
        "gs" => {
            let mut builder = GoogleCloudStorageBuilder::from_env().with_url(root);
            if !env_has("GOOGLE_TIMEOUT") {
                builder =
                    builder.with_config(GoogleConfigKey::Client(ClientConfigKey::Timeout), timeout);
            }
            Arc::new(
                builder
                    .with_retry(retry(&settings))
                    .with_http_connector(CountingConnector)
                    .build()?,
            )
        }
        "az" | "adl" | "azure" | "abfs" | "abfss" => {
            let mut builder = MicrosoftAzureBuilder::from_env().with_url(root);
            if !env_has("AZURE_TIMEOUT") {
                builder =
                    builder.with_config(AzureConfigKey::Client(ClientConfigKey::Timeout), timeout);
            }
            Arc::new(
                builder
                    .with_retry(retry(&settings))
                    .with_http_connector(CountingConnector)
                    .build()?,
            )
        }
        _ => Arc::new(
            HttpBuilder::new()
                .with_url(root)
                .with_config(ClientConfigKey::Timeout, timeout)
                .with_config(
                    ClientConfigKey::AllowHttp,
                    (url.scheme() == "http").to_string(),
                )
                .with_retry(retry(&settings))
                .with_http_connector(CountingConnector)
                .build()?,
        ),
    })
}
