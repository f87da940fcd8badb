//! Drives in object storage (S3, GCS, Azure Blob, any S3-speaking server, plain HTTPS):
//! the remote side of `source/`'s one notion of a byte source. An [`McapFile`] whose
//! path is an object URL reads through a [`RemoteObject`] instead of a file handle; every
//! layer above `source/` sees the same reads and the same errors.
//!
//! * `url`: telling an object URL from a local path, and splitting it.
//! * `store`: one `object_store` client per bucket, built from the usual environment
//!   variables, with bounded retries and timeouts, on a runtime of its own.
//! * `object`: one object's ranged reads, each pinned to the ETag it was listed with
//!   (`If-Match`), with a suffix read for the footer and summary and read-ahead while
//!   a scan goes through it.
//! * `listing`: listing prefixes (every page) and what a listing learned of each object,
//!   so that opening a listed object costs no request.
//! * `prefetch`: reads issued ahead of the samples that need them, bounded in bytes.
//! * `disk`: the optional local chunk cache, bounded in bytes, least recently used out.
//! * `stats`, `connector`: what every request did, for the Prometheus endpoint.
//!
//! [`McapFile`]: super::McapFile

mod connector;
mod disk;
mod listing;
mod object;
mod prefetch;
pub mod stats;
mod store;
mod url;

pub use disk::{DiskCacheSettings, configure as configure_disk_cache};
pub use listing::{list_dir, object_size};
pub(super) use object::RemoteObject;
pub(super) use prefetch::start as start_prefetch;
pub use store::{RemoteSettings, configure, settings};
pub use url::{ObjectUrl, is_remote};

use std::path::Path;

/// The text of an object store's error with anything secret taken out: query strings
/// (SAS tokens, signatures) and the values of the credential variables.
fn redact(text: &str) -> String {
    // The query string of every URL (up to the next blank or quote).
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find("://") {
        let start = rest[..at]
            .rfind(|c: char| c.is_whitespace() || c == '"' || c == '\'' || c == '(')
            .map_or(0, |i| i + 1);
        let end = rest[at..]
            .find(|c: char| c.is_whitespace() || c == '"' || c == '\'' || c == ')')
            .map_or(rest.len(), |i| at + i);
        out.push_str(&rest[..start]);
        let url = &rest[start..end];
        match url.split_once('?') {
            Some((base, _)) => {
                out.push_str(base);
                out.push_str("?…");
            }
            None => out.push_str(url),
        }
        rest = &rest[end..];
    }
    out.push_str(rest);
    for key in SECRET_VARIABLES {
        if let Ok(value) = std::env::var(key)
            && value.len() >= 4
        {
            out = out.replace(&value, "***");
        }
    }
    out
}

/// Environment variables whose values must never reach a log, error or metric.
const SECRET_VARIABLES: &[&str] = &[
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN",
    "AWS_ACCESS_KEY_ID",
    "AZURE_STORAGE_ACCOUNT_KEY",
    "AZURE_STORAGE_ACCESS_KEY",
    "AZURE_STORAGE_SAS_KEY",
    "AZURE_STORAGE_SAS_TOKEN",
    "AZURE_STORAGE_TOKEN",
    "AZURE_CLIENT_SECRET",
    "GOOGLE_SERVICE_ACCOUNT_KEY",
];

/// Where the credentials of a store come from, for an error that says what to set.
fn credential_hint(url: &ObjectUrl) -> &'static str {
    match url.scheme() {
        "s3" | "s3a" => {
            "check AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN), \
             AWS_REGION and, for MinIO or Ceph, AWS_ENDPOINT_URL; AWS_PROFILE is not read"
        }
        "gs" => "check GOOGLE_APPLICATION_CREDENTIALS (or GOOGLE_SERVICE_ACCOUNT)",
        "az" | "adl" | "azure" | "abfs" | "abfss" => {
            "check AZURE_STORAGE_ACCOUNT_NAME with AZURE_STORAGE_ACCOUNT_KEY, \
             AZURE_STORAGE_SAS_KEY or AZURE_CLIENT_ID/AZURE_CLIENT_SECRET/AZURE_TENANT_ID"
        }
        _ => "the server refused the request",
    }
}

/// An object store's error as a [`SourceError`](super::SourceError) naming `path`:
/// a refused precondition is a replaced object, refused credentials name the variables
/// to check, everything else says what the store said (redacted).
fn source_error(path: &Path, url: &ObjectUrl, e: object_store::Error) -> super::SourceError {
    use object_store::Error as E;
    let path = path.to_path_buf();
    match e {
        E::Precondition { .. } => super::SourceError::Replaced { path },
        E::PermissionDenied { .. } | E::Unauthenticated { .. } => super::SourceError::Remote {
            reason: format!(
                "the store refused the credentials ({}); {}",
                redact(&e.to_string()),
                credential_hint(url)
            ),
            path,
        },
        E::NotFound { .. } => super::SourceError::Remote {
            path,
            reason: "no such object (or bucket)".into(),
        },
        other => {
            let text = redact(&other.to_string());
            // Some servers answer a bad signature with a plain 403 that object_store
            // reports as a generic error.
            let refused = text.contains("403") || text.contains("401");
            super::SourceError::Remote {
                reason: if refused {
                    format!(
                        "the store refused the request ({text}); {}",
                        credential_hint(url)
                    )
                } else {
                    text
                },
                path,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn redact_drops_query_strings_and_secret_values() {
        let text = "GET https://acct.blob.core.windows.net/c/k.mcap?sig=abc&se=1 failed: 403";
        let out = redact(text);
        assert!(!out.contains("sig=abc"), "{out}");
        assert!(out.contains("k.mcap?… failed: 403"), "{out}");
        let xml = "404: <?xml version=\"1.0\"?><Code>NoSuchBucket</Code>";
        assert_eq!(redact(xml), xml);
    }
}
