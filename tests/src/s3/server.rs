//! A real S3 endpoint on 127.0.0.1 for the object-storage tests: moto's server in a child
//! python process (`tests/python/s3_server.py`), and the uploads, deletions and bucket
//! creation the tests prepare drives with. Object operations go through `object_store`,
//! the client the pipeline itself uses; buckets are created with a plain HTTP `PUT`, which
//! `object_store` cannot send.
//!
//! The script serves until its stdin closes, so the server dies with the test process
//! even if it is killed; dropping an [`S3Server`] kills and reaps it at once.

use futures::StreamExt as _;
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::path::Path as ObjectPath;
use object_store::{ObjectStoreExt as _, PutPayload};
use std::io::{Read as _, Write as _};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

/// Bound on moto's start (python imports moto, boto and flask: ~0.5 s idle, more on a
/// busy machine).
const START_TIMEOUT: Duration = Duration::from_secs(60);
/// Uploads in flight at once in [`S3Server::put_many`].
const PUT_CONCURRENCY: usize = 16;
/// The hint every start failure carries.
const INSTALL: &str = "pip install -r tests/python/requirements.txt";

/// An access key pair.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Credentials {
    /// `AWS_ACCESS_KEY_ID`.
    pub access_key_id: String,
    /// `AWS_SECRET_ACCESS_KEY`.
    pub secret_access_key: String,
}

impl Credentials {
    /// `test` / `test`: what a server without authentication accepts (as it accepts any).
    pub fn test() -> Self {
        Self {
            access_key_id: "test".into(),
            secret_access_key: "test".into(),
        }
    }
}

/// moto's S3 server on a free port of 127.0.0.1; killed and reaped when dropped.
///
/// The methods block (on the server's own tokio runtime) and panic on failure: call them
/// from plain `#[test]`s or `spawn_blocking`, not from inside an async runtime.
#[derive(Debug)]
pub struct S3Server {
    child: Option<Child>,
    port: u16,
    /// The credentials the harness's own requests use.
    credentials: Credentials,
    /// Whether moto checks signatures (bucket creation then turns it off around its
    /// unsigned `PUT`).
    auth: bool,
    runtime: tokio::runtime::Runtime,
}

impl S3Server {
    /// Starts a server that accepts any credentials. Panics (saying how to install moto)
    /// if it does not start within a minute.
    pub fn start() -> Self {
        let (child, ready) = spawn(false);
        Self::new(child, &ready, None)
    }

    /// Starts a server that checks SigV4 signatures against its IAM users: the
    /// credentials returned (an IAM user with an `s3:*` policy) are the only valid ones;
    /// any other key is refused with `403 InvalidAccessKeyId`, a wrong secret with
    /// `403 SignatureDoesNotMatch`. Unsigned requests other than bucket creation get a
    /// 500 from moto.
    pub fn start_with_auth() -> (Self, Credentials) {
        let (child, ready) = spawn(true);
        let field = |name: &str| {
            ready[name]
                .as_str()
                .map(str::to_owned)
                .unwrap_or_else(|| panic!("s3_server.py --auth printed no {name}: {ready}"))
        };
        let credentials = Credentials {
            access_key_id: field("access_key_id"),
            secret_access_key: field("secret_access_key"),
        };
        let server = Self::new(child, &ready, Some(credentials.clone()));
        (server, credentials)
    }

    fn new(mut child: Child, ready: &serde_json::Value, credentials: Option<Credentials>) -> Self {
        let Some(port) = ready["port"].as_u64().and_then(|p| u16::try_from(p).ok()) else {
            let _ = child.kill();
            let _ = child.wait();
            panic!("s3_server.py printed no port: {ready}");
        };
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("s3-server-harness")
            .enable_all()
            .build()
            .unwrap_or_else(|e| panic!("S3Server: tokio runtime: {e}"));
        Self {
            child: Some(child),
            port,
            auth: credentials.is_some(),
            credentials: credentials.unwrap_or_else(Credentials::test),
            runtime,
        }
    }

    /// `http://127.0.0.1:PORT`.
    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// The port moto listens on.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// The credentials the harness's own requests use (`test`/`test`, or the IAM user's
    /// with authentication on).
    pub fn credentials(&self) -> &Credentials {
        &self.credentials
    }

    /// Runs `future` to completion on the harness's runtime.
    pub fn block_on<F: std::future::Future>(&self, future: F) -> F::Output {
        self.runtime.block_on(future)
    }

    /// An `object_store` client of `bucket` at moto itself, with the harness's credentials.
    pub fn store(&self, bucket: &str) -> AmazonS3 {
        self.store_at(&self.endpoint(), bucket, &self.credentials)
    }

    /// An `object_store` client of `bucket` at `endpoint` (moto's, or a proxy's in front
    /// of it) with `credentials`, plain HTTP allowed, path-style, default retries.
    pub fn store_at(&self, endpoint: &str, bucket: &str, credentials: &Credentials) -> AmazonS3 {
        AmazonS3Builder::new()
            .with_endpoint(endpoint)
            .with_allow_http(true)
            .with_access_key_id(&credentials.access_key_id)
            .with_secret_access_key(&credentials.secret_access_key)
            .with_region("us-east-1")
            .with_bucket_name(bucket)
            .build()
            .unwrap_or_else(|e| panic!("object_store client of {bucket} at {endpoint}: {e}"))
    }

    /// Creates `bucket` (a name S3 accepts: 3 to 63 lowercase letters, digits, dots and
    /// hyphens); creating one that exists succeeds.
    pub fn create_bucket(&self, bucket: &str) {
        if self.auth {
            self.moto_api_post("/moto-api/reset-auth", "inf");
        }
        let (status, body) = self
            .raw_request("PUT", &format!("/{bucket}"), "", "")
            .unwrap_or_else(|e| panic!("creating bucket {bucket}: {e}"));
        if self.auth {
            self.moto_api_post("/moto-api/reset-auth", "0");
        }
        assert!(
            (200..300).contains(&status),
            "creating bucket {bucket}: HTTP {status}: {body}"
        );
    }

    /// Writes `bytes` to `bucket`/`key` in one `PUT` (its ETag is then the quoted hex MD5
    /// of the bytes); returns the ETag as S3 sends it, quotes included.
    pub fn put(&self, bucket: &str, key: &str, bytes: &[u8]) -> String {
        let store = self.store(bucket);
        let result = self
            .block_on(store.put(&ObjectPath::from(key), PutPayload::from(bytes.to_vec())))
            .unwrap_or_else(|e| panic!("PUT {bucket}/{key}: {e}"));
        result
            .e_tag
            .unwrap_or_else(|| panic!("PUT {bucket}/{key}: no ETag"))
    }

    /// Deletes `bucket`/`key` (deleting a missing key succeeds, as in S3).
    pub fn delete(&self, bucket: &str, key: &str) {
        let store = self.store(bucket);
        self.block_on(store.delete(&ObjectPath::from(key)))
            .unwrap_or_else(|e| panic!("DELETE {bucket}/{key}: {e}"));
    }

    /// Writes many objects, 16 `PUT`s in flight at once (moto takes ~3 ms a `PUT`:
    /// 1 100 small objects in a few seconds).
    pub fn put_many<K, B>(&self, bucket: &str, items: impl IntoIterator<Item = (K, B)>)
    where
        K: Into<String>,
        B: Into<Vec<u8>>,
    {
        let store = self.store(bucket);
        let store = &store;
        let puts = items.into_iter().map(|(key, bytes)| {
            let key: String = key.into();
            let payload = PutPayload::from(bytes.into());
            async move {
                store
                    .put(&ObjectPath::from(key.as_str()), payload)
                    .await
                    .map_err(|e| format!("PUT {bucket}/{key}: {e}"))
            }
        });
        self.block_on(async {
            let mut results = futures::stream::iter(puts).buffer_unordered(PUT_CONCURRENCY);
            while let Some(result) = results.next().await {
                if let Err(e) = result {
                    panic!("{e}");
                }
            }
        });
    }

    /// Uploads local `files` to `bucket` under `prefix`, each as `prefix/<its file name>`
    /// ([`put_many`](Self::put_many)); returns the URL of the prefix,
    /// `s3://bucket/prefix/`.
    pub fn upload<P: AsRef<std::path::Path>>(
        &self,
        bucket: &str,
        prefix: &str,
        files: &[P],
    ) -> String {
        let prefix = prefix.trim_matches('/');
        let items: Vec<(String, Vec<u8>)> = files
            .iter()
            .map(|file| {
                let file = file.as_ref();
                let name = file
                    .file_name()
                    .unwrap_or_else(|| panic!("uploading {}: no file name", file.display()))
                    .to_string_lossy();
                let bytes = std::fs::read(file)
                    .unwrap_or_else(|e| panic!("uploading {}: {e}", file.display()));
                (format!("{prefix}/{name}"), bytes)
            })
            .collect();
        self.put_many(bucket, items);
        format!("s3://{bucket}/{prefix}/")
    }

    /// The environment a child process (the pipeline, through `object_store`'s
    /// `AmazonS3Builder::from_env`) needs to reach this server's buckets at
    /// `bucket_endpoint` (this server's [`endpoint`](Self::endpoint) or a proxy's in front
    /// of it), with the harness's credentials.
    pub fn env(&self, bucket_endpoint: &str) -> Vec<(String, String)> {
        [
            ("AWS_ENDPOINT_URL", bucket_endpoint),
            ("AWS_ALLOW_HTTP", "true"),
            ("AWS_ACCESS_KEY_ID", &self.credentials.access_key_id),
            ("AWS_SECRET_ACCESS_KEY", &self.credentials.secret_access_key),
            ("AWS_REGION", "us-east-1"),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v.to_owned()))
        .collect()
    }

    /// `POST`s `body` to one of moto's own endpoints (`/moto-api/…`, never authenticated).
    fn moto_api_post(&self, path: &str, body: &str) {
        match self.raw_request("POST", path, "Content-Type: text/plain\r\n", body) {
            Ok((200, _)) => {}
            Ok((status, body)) => panic!("POST {path}: HTTP {status}: {body}"),
            Err(e) => panic!("POST {path}: {e}"),
        }
    }

    /// One unsigned HTTP/1.1 request on its own connection: (status, body).
    fn raw_request(
        &self,
        method: &str,
        path: &str,
        extra_headers: &str,
        body: &str,
    ) -> std::io::Result<(u16, String)> {
        let mut stream = TcpStream::connect(("127.0.0.1", self.port))?;
        stream.set_read_timeout(Some(Duration::from_secs(30)))?;
        write!(
            stream,
            "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\n{extra_headers}\
             Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            self.port,
            body.len()
        )?;
        let mut response = Vec::new();
        stream.read_to_end(&mut response)?;
        let text = String::from_utf8_lossy(&response);
        let status = text
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .ok_or_else(|| {
                std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    format!("no HTTP status in {text:?}"),
                )
            })?;
        let body = text
            .split_once("\r\n\r\n")
            .map(|(_, b)| b.to_owned())
            .unwrap_or_default();
        Ok((status, body))
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Starts `s3_server.py` and reads its ready line (JSON: the port, and the credentials
/// with `--auth`).
fn spawn(auth: bool) -> (Child, serde_json::Value) {
    let script = crate::workspace_root().join("tests/python/s3_server.py");
    let mut command = Command::new("python3");
    command
        .arg(&script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit());
    if auth {
        command.arg("--auth");
    }
    let mut child = command.spawn().unwrap_or_else(|e| {
        panic!(
            "starting python3 {} failed ({e}): is python3 installed? {INSTALL}",
            script.display()
        )
    });
    let Some(stdout) = child.stdout.take() else {
        panic!("s3_server.py: no stdout pipe");
    };
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut line = String::new();
        let read = std::io::BufRead::read_line(&mut std::io::BufReader::new(stdout), &mut line);
        let _ = tx.send(read.map(|_| line));
    });
    let line = match rx.recv_timeout(START_TIMEOUT) {
        Ok(Ok(line)) if !line.trim().is_empty() => line,
        outcome => {
            let _ = child.kill();
            let status = child.wait();
            panic!(
                "the local S3 server (moto, {}) did not start within {START_TIMEOUT:?} \
                 ({outcome:?}, exit {status:?}; its stderr is above). {INSTALL}",
                script.display()
            );
        }
    };
    match serde_json::from_str(&line) {
        Ok(ready) => (child, ready),
        Err(e) => {
            let _ = child.kill();
            let _ = child.wait();
            panic!("s3_server.py printed {line:?}, not JSON ({e}). {INSTALL}");
        }
    }
}
