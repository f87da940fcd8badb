//! The harness against itself, with `object_store` as the client: what moto serves, and
//! what the proxy counts and injects, as the object-storage reader's tests rely on.

use super::*;
use futures::TryStreamExt as _;
use object_store::path::Path as ObjectPath;
use object_store::{GetOptions, ObjectStore as _, ObjectStoreExt as _};
use std::time::{Duration, Instant};

/// A deterministic body of `n` bytes.
fn body(n: usize) -> Vec<u8> {
    (0..n).map(|i| (i * 31 % 251) as u8).collect()
}

/// moto with `bucket` holding `key` = `bytes`.
fn server_with(bucket: &str, key: &str, bytes: &[u8]) -> S3Server {
    let server = S3Server::start();
    server.create_bucket(bucket);
    server.put(bucket, key, bytes);
    server
}

#[test]
fn put_gives_md5_etag_and_ranged_get_through_proxy() {
    let bytes = body(100_000);
    let server = S3Server::start();
    server.create_bucket("ranged");
    let etag = server.put("ranged", "drives/a.mcap", &bytes);
    // S3's ETag of a single PUT: the quoted hex MD5 (here of a known 3-byte body).
    assert_eq!(
        server.put("ranged", "abc", b"abc"),
        "\"900150983cd24fb0d6963f7d28e17f72\""
    );
    assert!(etag.starts_with('"') && etag.len() == 34, "{etag}");

    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let store = server.store_at(&proxy.endpoint(), "ranged", server.credentials());
    let path = ObjectPath::from("drives/a.mcap");
    let got = server
        .block_on(store.get_range(&path, 1_000..41_000))
        .unwrap();
    assert_eq!(&got[..], &bytes[1_000..41_000]);
    let meta = server.block_on(store.head(&path)).unwrap();
    assert_eq!(meta.size, bytes.len() as u64);
    assert_eq!(meta.e_tag.as_deref(), Some(etag.as_str()));
    // A suffix range (the MCAP footer read): the last 30 bytes.
    let options = GetOptions {
        range: Some(object_store::GetRange::Suffix(30)),
        ..GetOptions::default()
    };
    let tail = server
        .block_on(async { store.get_opts(&path, options).await?.bytes().await })
        .unwrap();
    assert_eq!(&tail[..], &bytes[bytes.len() - 30..]);

    let counters = proxy.counters();
    assert_eq!(counters.ranged_get, 2, "{counters:?}");
    assert_eq!(counters.head, 1, "{counters:?}");
    assert_eq!(counters.body_bytes, 40_030, "{counters:?}");
    assert_eq!(counters.faults.total(), 0);

    server.delete("ranged", "drives/a.mcap");
    let gone = server.block_on(store.head(&path));
    assert!(
        matches!(gone, Err(object_store::Error::NotFound { .. })),
        "{gone:?}"
    );
}

#[test]
fn list_pages_past_a_thousand_keys() {
    let server = S3Server::start();
    server.create_bucket("many");
    let started = Instant::now();
    server.put_many(
        "many",
        (0..1_100).map(|i| (format!("drives/{i:05}.mcap"), vec![b'x'; 8])),
    );
    let upload = started.elapsed();
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let store = server.store_at(&proxy.endpoint(), "many", server.credentials());
    let listed: Vec<_> = server
        .block_on(store.list(Some(&ObjectPath::from("drives"))).try_collect())
        .unwrap();
    assert_eq!(listed.len(), 1_100, "uploads took {upload:?}");
    let counters = proxy.counters();
    assert!(counters.list >= 2, "{counters:?}");
    assert_eq!(counters.requests(), counters.list, "{counters:?}");
}

#[test]
fn slowdown_once_per_request_is_retried() {
    let bytes = body(50_000);
    let server = server_with("slowdown", "k", &bytes);
    let proxy = FaultProxy::start(
        &server.endpoint(),
        FaultPlan {
            p_503: 1.0,
            fail_once: true,
            ..FaultPlan::default()
        },
    );
    let store = server.store_at(&proxy.endpoint(), "slowdown", server.credentials());
    let path = ObjectPath::from("k");
    let got = server.block_on(store.get_range(&path, 0..20_000)).unwrap();
    assert_eq!(&got[..], &bytes[..20_000]);
    let got = server
        .block_on(async { store.get(&path).await?.bytes().await })
        .unwrap();
    assert_eq!(&got[..], &bytes[..]);
    let counters = proxy.counters();
    assert_eq!(counters.faults.status_503, 2, "{counters:?}");
    assert_eq!(counters.ranged_get, 2, "{counters:?}");
    assert_eq!(counters.get_object, 2, "{counters:?}");

    // Only the plan's first request fails (its retry is the second).
    proxy.set_plan(FaultPlan {
        p_500: 1.0,
        scope: FaultScope::NthRequest(1),
        ..FaultPlan::default()
    });
    proxy.reset_counters();
    server.block_on(store.head(&path)).unwrap();
    assert_eq!(proxy.counters().faults.status_500, 1);
    assert_eq!(proxy.counters().head, 2);
}

#[test]
fn cut_body_and_reset_are_resumed() {
    let bytes = body(300_000);
    let server = server_with("cut", "k", &bytes);
    let proxy = FaultProxy::start(
        &server.endpoint(),
        FaultPlan {
            p_cut: 1.0,
            scope: FaultScope::NthRequest(1),
            ..FaultPlan::default()
        },
    );
    let store = server.store_at(&proxy.endpoint(), "cut", server.credentials());
    let path = ObjectPath::from("k");
    let got = server
        .block_on(async { store.get(&path).await?.bytes().await })
        .unwrap();
    assert_eq!(&got[..], &bytes[..]);
    let counters = proxy.counters();
    assert_eq!(counters.faults.cut, 1, "{counters:?}");
    // The first GET is cut after half; the resume asks for the rest with a Range.
    assert_eq!(
        (counters.get_object, counters.ranged_get),
        (1, 1),
        "{counters:?}"
    );
    assert_eq!(counters.body_bytes, bytes.len() as u64, "{counters:?}");

    // A connection closed without any response: retried.
    proxy.set_plan(FaultPlan {
        p_reset: 1.0,
        fail_once: true,
        ..FaultPlan::default()
    });
    proxy.reset_counters();
    let got = server.block_on(store.get_range(&path, 10..20)).unwrap();
    assert_eq!(&got[..], &bytes[10..20]);
    assert_eq!(proxy.counters().faults.reset, 1);
    assert_eq!(proxy.counters().ranged_get, 2);
}

#[test]
fn latency_and_bandwidth_are_applied() {
    let bytes = body(100_000);
    let server = server_with("slow", "k", &bytes);
    let proxy = FaultProxy::start(
        &server.endpoint(),
        FaultPlan::latency(Duration::from_millis(50)),
    );
    let store = server.store_at(&proxy.endpoint(), "slow", server.credentials());
    let path = ObjectPath::from("k");
    server.block_on(store.head(&path)).unwrap(); // connection set up
    let started = Instant::now();
    for _ in 0..3 {
        server.block_on(store.get_range(&path, 0..10)).unwrap();
    }
    let three = started.elapsed();
    assert!(three >= Duration::from_millis(150), "{three:?}");

    proxy.set_plan(FaultPlan {
        bandwidth_bytes_per_sec: Some(500_000),
        ..FaultPlan::default()
    });
    let started = Instant::now();
    let got = server.block_on(store.get_range(&path, 0..100_000)).unwrap();
    let took = started.elapsed();
    assert_eq!(&got[..], &bytes[..]);
    // 100 kB at 500 kB/s.
    assert!(took >= Duration::from_millis(180), "{took:?}");
}

#[test]
fn wrong_if_match_is_refused() {
    let server = server_with("ifmatch", "k", b"0123456789");
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let store = server.store_at(&proxy.endpoint(), "ifmatch", server.credentials());
    let path = ObjectPath::from("k");
    let etag = server.block_on(store.head(&path)).unwrap().e_tag.unwrap();
    let get = |if_match: &str| {
        let options = GetOptions {
            if_match: Some(if_match.to_owned()),
            range: Some((2..5).into()),
            ..GetOptions::default()
        };
        server.block_on(async { store.get_opts(&path, options).await?.bytes().await })
    };
    assert_eq!(&get(&etag).unwrap()[..], b"234");
    let refused = get("\"00000000000000000000000000000000\"");
    assert!(
        matches!(refused, Err(object_store::Error::Precondition { .. })),
        "{refused:?}"
    );
}

#[test]
fn wrong_credentials_are_refused_with_auth() {
    let (server, credentials) = S3Server::start_with_auth();
    server.create_bucket("private");
    server.put("private", "k", b"secret");
    let proxy = FaultProxy::start(&server.endpoint(), FaultPlan::default());
    let path = ObjectPath::from("k");
    let read = |credentials: &Credentials| {
        let store = server.store_at(&proxy.endpoint(), "private", credentials);
        server.block_on(async { store.get(&path).await?.bytes().await })
    };
    assert_eq!(&read(&credentials).unwrap()[..], b"secret");
    for (wrong, code) in [
        (Credentials::test(), "InvalidAccessKeyId"),
        (
            Credentials {
                secret_access_key: "wrong".into(),
                ..credentials.clone()
            },
            "SignatureDoesNotMatch",
        ),
    ] {
        let refused = read(&wrong);
        let Err(err @ object_store::Error::PermissionDenied { .. }) = &refused else {
            panic!("{wrong:?} was not refused with 403: {refused:?}");
        };
        assert!(err.to_string().contains(code), "{err}");
    }
    // The environment a child process gets carries the valid key.
    let env = server.env(&proxy.endpoint());
    assert!(env.contains(&(
        "AWS_ACCESS_KEY_ID".into(),
        credentials.access_key_id.clone()
    )));
    assert!(env.contains(&("AWS_ENDPOINT_URL".into(), proxy.endpoint())));
}
