//! Signals sent to a child `xscale` the way `timeout`, `docker stop` or a batch scheduler does.

/// Send SIGTERM to `child` (with the system's `kill`, so the tests need no libc binding).
pub fn terminate(child: &std::process::Child) {
    let st = std::process::Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(st.success(), "kill -TERM {}", child.id());
}
