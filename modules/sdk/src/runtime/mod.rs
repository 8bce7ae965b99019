//! The module runtime, one unit in five files: the author's API (`author`: `Module`, `Setup`,
//! the port handles, `Io`), the shared-memory services a module and its DNM open
//! (`services`), services a dead process left half-created (`abandoned`), the module process
//! loop (`process`), and stepping a module without a DNM (`offline`). `Io` reads and writes through either side, the process's shared memory or
//! `Offline`, and both sides step an author's module through it.

pub(crate) mod abandoned;
pub(crate) mod author;
pub(crate) mod offline;
pub(crate) mod process;
pub(crate) mod services;
