//! Ports for the processes of a test or a benchmark (shared by both harnesses).

/// A TCP port free on loopback right now.
pub fn free_port() -> u16 {
    // Ports are often taken some time after they are chosen (a rig chooses all of its own
    // before it starts anything), and the kernel may offer a port it offered before in the
    // meantime: one never handed out in this process is taken.
    static GIVEN: std::sync::Mutex<Vec<u16>> = std::sync::Mutex::new(Vec::new());
    let mut given = GIVEN.lock().unwrap_or_else(|e| e.into_inner());
    loop {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        if !given.contains(&port) {
            given.push(port);
            return port;
        }
    }
}
