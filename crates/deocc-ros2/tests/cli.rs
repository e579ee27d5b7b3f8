//! `deocc-ros2` refuses bad settings and input with a message naming them and a non-zero exit,
//! before touching the network.
#![cfg(feature = "ros2")]

use std::process::Command;

fn run(args: &[&str]) -> (bool, String) {
    let o = Command::new(env!("CARGO_BIN_EXE_deocc-ros2"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn bad_settings_and_input_are_named() {
    let dir = std::env::temp_dir().join(format!("deocc-ros2-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let empty = dir.join("empty-token");
    std::fs::write(&empty, "  \n").unwrap();
    let empty = empty.to_str().unwrap();
    for (args, want) in [
        (
            &[
                "bridge",
                "--service",
                "http://127.0.0.1:9",
                "--token-file",
                empty,
            ][..],
            "the token is empty",
        ),
        (&["bridge", "--max-views", "0"][..], "--max-views"),
        (&["bridge", "--slop-ms=-1"][..], "--slop-ms"),
        (
            &["bridge", "--options", "/no/such/options.json"][..],
            "/no/such/options.json",
        ),
        (&["bridge", "--completer", "magic"][..], "magic"),
        (&["play", "/no/such/scene"][..], "/no/such/scene"),
        (&["play", "/tmp", "--period=-1"][..], "--period"),
        // These panicked (Duration::from_secs_f64) or bound wrapped ports.
        (&["play", "/tmp", "--period", "1e300"][..], "--period"),
        (&["play", "/tmp", "--timeout", "1e300"][..], "--timeout"),
        (&["bridge", "--domain-id", "300"][..], "--domain-id 300"),
        (
            &["play", "/tmp", "--domain-id", "233"][..],
            "--domain-id 233",
        ),
    ] {
        let (ok, err) = run(args);
        assert!(!ok, "{args:?} succeeded");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: {err}");
        assert!(
            err.starts_with("error") || err.contains("error:"),
            "{args:?}: {err}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
