// Percent-encoding of URI components (RFC 3986 §2.1), the one encoder every camera URI is built
// with (backends' device URIs, the CLI's sim:// options). Dependency-free: the CLI, which speaks
// only the C ABI, compiles this file too.
#pragma once

#include <optional>
#include <string>

namespace posecal {

// Keeps letters, digits and "-._~:@+,=/" (safe in a path and in a query value as Uri::parse reads
// it); every other byte becomes %XX.
std::string percent_encode(const std::string& text);

// Decodes %XX escapes; nullopt for a malformed escape.
std::optional<std::string> percent_decode(const std::string& text);

}  // namespace posecal
