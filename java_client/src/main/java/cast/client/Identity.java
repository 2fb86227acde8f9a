package cast.client;

/**
 * Who a component is: its id, its own subarchitecture, and whether it may write
 * every subarchitecture. Identity comes only from the token, which the server
 * verifies on every call; a component learns its identity from the server's answer
 * to its registration, not by decoding the token.
 *
 * @param componentId the component's id
 * @param subarchitecture its own SA
 * @param privileged whether it may write every SA
 */
public record Identity(String componentId, String subarchitecture, boolean privileged) {}
