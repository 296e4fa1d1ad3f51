//! Issue 35, a locked-down network: the node and the replays run with zenoh configs (passed
//! through `--zenoh-config` as they are) that use TLS with mutual authentication (a test CA
//! and certificates made at test time with the `openssl` command; without it the test fails
//! unless told to skip, [`crate::unavailable`]) and zenoh's access control on the node: only the certificate named
//! `replay` may put on the input key. A second publisher with a valid certificate of another
//! name (`intruder`) is connected and sees the node's subscriber, but its frames never reach
//! the node. And `--max-frame-bytes`: larger payloads are rejected before decoding.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use crate::transport_support::*;
use crate::unavailable::cannot_run;

/// A CA and, for each name, a key and a certificate signed by it (CN = name, SAN 127.0.0.1 and
/// localhost, usable as server and client); None when `openssl` cannot be run.
fn make_certs(dir: &Path, names: &[&str]) -> Option<()> {
    let run = |args: &[&str]| -> Option<()> {
        let o = Command::new("openssl")
            .args(args)
            .current_dir(dir)
            .output()
            .ok()?;
        assert!(
            o.status.success(),
            "openssl {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        Some(())
    };
    let ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"];
    let mut ca = vec!["req", "-x509", "-nodes", "-days", "2"];
    ca.extend(ec);
    ca.extend([
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-subj",
        "/CN=minflow test CA",
        "-addext",
        "basicConstraints=critical,CA:TRUE",
        "-addext",
        "keyUsage=critical,keyCertSign,cRLSign",
    ]);
    run(&ca)?;
    std::fs::write(
        dir.join("leaf.ext"),
        "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\n\
         extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=IP:127.0.0.1,DNS:localhost\n",
    )
    .unwrap();
    for (serial, name) in names.iter().enumerate() {
        let (key, csr, pem) = (
            format!("{name}.key"),
            format!("{name}.csr"),
            format!("{name}.pem"),
        );
        let subject = format!("/CN={name}");
        let mut req = vec!["req", "-nodes"];
        req.extend(ec);
        req.extend(["-keyout", &key, "-out", &csr, "-subj", &subject]);
        run(&req)?;
        let serial = (serial + 2).to_string();
        run(&[
            "x509",
            "-req",
            "-in",
            &csr,
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-set_serial",
            &serial,
            "-days",
            "2",
            "-extfile",
            "leaf.ext",
            "-out",
            &pem,
        ])?;
    }
    Some(())
}

/// The TLS part of a zenoh config for the certificate `name` in `dir` (mutual TLS, TLS only).
fn tls(dir: &Path, name: &str) -> String {
    let f = |file: String| dir.join(file).display().to_string();
    format!(
        r#"transport: {{ link: {{ protocols: ["tls"], tls: {{
            root_ca_certificate: "{}",
            listen_private_key: "{key}", listen_certificate: "{pem}",
            connect_private_key: "{key}", connect_certificate: "{pem}",
            enable_mtls: true }} }} }},
          scouting: {{ multicast: {{ enabled: false }}, gossip: {{ enabled: false }} }},"#,
        f("ca.pem".into()),
        key = f(format!("{name}.key")),
        pem = f(format!("{name}.pem")),
    )
}

/// The node's config: listens on TLS at `port`; access control lets only the certificate
/// `replay` put on `key`, and everyone declare subscriptions, tokens and queries.
fn node_config(dir: &Path, port: u16, key: &str) -> PathBuf {
    let text = format!(
        r#"{{ mode: "peer", listen: {{ endpoints: ["tls/127.0.0.1:{port}"] }},
          {}
          access_control: {{
            enabled: true,
            default_permission: "deny",
            rules: [
              {{ id: "frames", permission: "allow", flows: ["ingress"], messages: ["put"],
                 key_exprs: ["{key}"] }},
              {{ id: "declares", permission: "allow", flows: ["ingress"],
                 messages: ["declare_subscriber", "declare_queryable", "query", "reply",
                            "liveliness_token", "liveliness_query",
                            "declare_liveliness_subscriber"],
                 key_exprs: ["**"] }},
              {{ id: "out", permission: "allow", flows: ["egress"],
                 messages: ["put", "delete", "declare_subscriber", "declare_queryable", "query",
                            "reply", "liveliness_token", "liveliness_query",
                            "declare_liveliness_subscriber"],
                 key_exprs: ["**"] }},
            ],
            subjects: [ {{ id: "replay", cert_common_names: ["replay"] }}, {{ id: "anyone" }} ],
            policies: [
              {{ rules: ["frames"], subjects: ["replay"] }},
              {{ rules: ["declares", "out"], subjects: ["anyone"] }},
            ],
          }} }}"#,
        tls(dir, "node")
    );
    let path = dir.join("node.json5");
    std::fs::write(&path, text).unwrap();
    path
}

/// A publisher's config: connects to the node at `port` with the certificate `name`.
fn client_config(dir: &Path, port: u16, name: &str) -> PathBuf {
    let text = format!(
        r#"{{ mode: "peer", connect: {{ endpoints: ["tls/127.0.0.1:{port}"] }},
          listen: {{ endpoints: [] }},
          {} }}"#,
        tls(dir, name)
    );
    let path = dir.join(format!("{name}.json5"));
    std::fs::write(&path, text).unwrap();
    path
}

fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    l.local_addr().unwrap().port()
}

fn small_model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small")
}

#[test]
fn locked_down_zenoh_predicts_only_on_the_authorised_publisher() {
    let dir = crate::tmp::tempdir().unwrap();
    if make_certs(dir.path(), &["node", "replay", "intruder"]).is_none() {
        return cannot_run("no `openssl` command to make the test certificates");
    }
    let port = free_port();
    let input = unique_topic("acl_in");
    let key = input.trim_start_matches('/');
    let model = small_model();
    let node_cfg = node_config(dir.path(), port, key);
    let node = Node::spawn(
        "node",
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--zenoh-config",
            node_cfg.to_str().unwrap(),
            "--in",
            &input,
            "--out",
            &unique_topic("acl_out"),
            "--status",
            "none",
            "--queue-depth",
            "64",
        ],
    );
    let source = source_bag();
    let play = |name: &str| {
        let cfg = client_config(dir.path(), port, name);
        let o = Node::spawn(
            name,
            &[
                "replay",
                source.to_str().unwrap(),
                "--topic",
                &input,
                "--zenoh-config",
                cfg.to_str().unwrap(),
            ],
        )
        .wait(Duration::from_secs(60));
        ok(&o, name)
    };
    // The intruder's TLS session is accepted (its certificate is the CA's) and it sees the
    // node's subscriber, so it publishes all 25 frames; access control drops them.
    let intruder = play("intruder");
    assert!(intruder.contains("25 frame"), "{intruder}");
    std::thread::sleep(Duration::from_secs(1));
    play("replay");
    std::thread::sleep(Duration::from_secs(2));
    node.signal("INT");
    let log = ok(&node.wait(Duration::from_secs(30)), "node");
    assert_eq!(counter(&log, "received"), Some(25), "{log}");
    assert_eq!(counter(&log, "predicted"), Some(25), "{log}");
}

#[test]
fn frames_over_max_frame_bytes_are_rejected_before_decoding() {
    let input = unique_topic("maxbytes");
    let model = small_model();
    let node = Node::spawn(
        "node",
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--in",
            &input,
            "--out",
            &unique_topic("maxbytes_out"),
            "--status",
            "none",
            "--max-frame-bytes",
            "10000",
        ],
    );
    let source = source_bag();
    ok(
        &Node::spawn(
            "replay",
            &["replay", source.to_str().unwrap(), "--topic", &input],
        )
        .wait(Duration::from_secs(60)),
        "replay",
    );
    std::thread::sleep(Duration::from_secs(1));
    node.signal("INT");
    let log = ok(&node.wait(Duration::from_secs(30)), "node");
    assert_eq!(counter(&log, "received"), Some(25), "{log}");
    assert_eq!(counter(&log, "rejected"), Some(25), "{log}");
    assert_eq!(counter(&log, "predicted"), Some(0), "{log}");
    assert!(log.contains("over --max-frame-bytes 10000"), "{log}");
}
